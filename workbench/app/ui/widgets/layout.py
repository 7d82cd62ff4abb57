"""What viser's panel cannot lay out by itself, as CSS put into the page (an HTML element holding a <style>): the
run's buttons (Step, Run, Pause, Reset) on one row, so that the panel's fixed top leaves room for the tabs.

Viser draws each button full-width in a block of its own (``<div><button id=UUID>``); the rule selects those
blocks by their button's id, which is the handle's uuid."""

from __future__ import annotations


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
