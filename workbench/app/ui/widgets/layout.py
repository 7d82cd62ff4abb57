"""What viser's panel cannot lay out by itself, as CSS put into the page (an HTML element holding a <style>): the
run's buttons (Step, Run, Pause, Reset) on one row, so that the panel's fixed top leaves room for the tabs.

Viser draws each button full-width in a block of its own (``<div><button id=UUID>``); the rule selects those
blocks by their button's id, which is the handle's uuid."""

from __future__ import annotations

# Markdown tables (the truth table, the posterior, the sequence's frames) get no cell spacing from viser: their
# columns ran together ("2.7right1.00"). A cell's text stays on one line (a header may wrap), and a table wider
# than the panel scrolls rather than being clipped. uPlot's legends are tables too, with their own layout.
TABLE_CSS = ("<style>table:not(.u-legend){display:block;max-width:100%;overflow-x:auto;font-size:0.8rem}"
             "table:not(.u-legend) :is(th, td){padding:0.1rem 0.4rem}"
             "table:not(.u-legend) td{white-space:nowrap}"
             "table:not(.u-legend) :is(th, td):first-child{padding-left:0}</style>")


def without_number_box(gui, slider) -> None:
    """Hide the number box viser draws beside ``slider`` (the box follows the slider in its row): the browser reads
    what is typed there its own way (``1e1`` as 11, ``12,5`` as 125) and says nothing, against the panel's one rule
    for typed numbers (``numeric``). The slider is still dragged, or moved with the arrow keys."""
    gui.add_html(f'<style>div[id="{slider._impl.uuid}"] + .mantine-NumberInput-root{{display:none}}</style>')


def button_row_css(uuids: list[str]) -> str:
    """A <style> putting the blocks of the buttons ``uuids`` side by side, equal widths, on one row."""
    share = 100.0 / max(1, len(uuids))
    # Each block keeps viser's horizontal margin (0.625 rem a side), so its width leaves that room.
    rules = "".join(
        f'div:has(> button[id="{u}"]){{display:inline-block;vertical-align:top;'
        f"width:calc({share:.4f}% - 1.25rem)}}"
        f'button[id="{u}"]{{padding-left:0.4rem;padding-right:0.4rem}}'
        for u in uuids)
    return f"<style>{rules}</style>"
