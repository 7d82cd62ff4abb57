"""The Estimator tab's settings: what the run uses (``config``, ``likelihood``) against what is typed. Valid values
go to the engine at once (the seed and the likelihood wait for Reset, and the tab says so); refused ones are outlined
and listed, and put back to the value in use once the typing pauses or at Step, Run or Reset."""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import viser

from workbench.app import protocol as p
from workbench.app.ui.reporting import Reporter
from workbench.app.ui.run.estimator_tab import SEED, build_estimator_tab, pending_markdown
from workbench.app.ui.ui_thread import UiThread
from workbench.app.ui.widgets.numeric import Refusals
from workbench.app.ui.widgets.quiet import Quiet
from workbench.errors import InputError
from workbench.inference.config import EstimatorConfig


class SettingsForm:
    """The Estimator tab (``container``): builds its controls (``tab``) and sends what is typed with ``send``."""

    def __init__(self, gui: viser.GuiApi, container: viser.GuiTabHandle, ui: UiThread, quiet: Quiet,
                 reporter: Reporter, send: Callable[[object], None], config: EstimatorConfig, likelihood: str):
        self.ui, self.quiet, self.reporter, self.send = ui, quiet, reporter, send
        self.config = config
        self.likelihood = likelihood  # the likelihood model of the run (the tab's applies at Reset)
        with container:
            self.tab = build_estimator_tab(gui, config, likelihood)
        self.refusals = Refusals(ui, quiet, reporter, lambda: self.tab.field_ids,
                                 lambda labels: self.tab.revert(labels, self.config))
        for h in (self.tab.method, *self.tab.fields.values()):
            h.on_update(ui.callback(lambda _: self.changed()))
        self.tab.likelihood.on_update(ui.callback(lambda _: self.show_pending()))

    def changed(self) -> None:
        """A setting was typed: the valid ones go to the engine at once (the seed waits for Reset); refused ones
        are outlined and listed now, and put back to the value in use once the typing pauses (``Refusals``) or at
        Step, Run or Reset."""
        if self.quiet.active:
            return  # a restored session's settings being shown, not a user's edit
        try:
            config, errors = self.tab.read_config(self.config)
        except InputError as err:
            self.reporter.report(p.Failure("Input error", err.problem, err.path))
            return
        self.refusals.refuse(errors)
        config = replace(config, seed=self.config.seed)  # the seed applies at Reset
        if config != self.config:
            self.config = config
            self.send(p.SetConfig(self.config))
        self.show_pending()

    def revert(self) -> bool:
        """Put the values in use back into the fields that hold refused ones (they stay outlined and listed)
        -> whether any was refused."""
        return self.refusals.put_back()

    def show_pending(self) -> None:
        """Say which settings wait for Reset (likelihood, seed), and which apply at once."""
        if self.quiet.active:
            return
        try:
            seed = SEED.parse(self.tab.seed.value)
        except InputError:
            seed = self.config.seed
        content = pending_markdown((self.likelihood, self.config.seed), (self.tab.likelihood.value, seed))
        if self.tab.pending.content != content:
            self.tab.pending.content = content

    def for_reset(self) -> p.Reset:
        """Every typed setting, the seed and the likelihood included, taken for the run -> the Reset to send."""
        self.revert()
        self.config = self.tab.estimator_config(self.config)
        self.likelihood = self.tab.likelihood.value
        self.show_pending()
        return p.Reset(self.config, self.likelihood)

    def cancel(self) -> None:
        """No refused value is put back later (one is now, or the app stops)."""
        self.refusals.cancel()
