"""The Label tab's choice of mode: per object with more than one mode, a dropdown of its modes ("mode 1 · p = 0.62 ·
the estimate", "mode 2 · p = 0.38 · turned over its x axis"), the top one chosen whenever a new posterior
arrives. "Use best estimate as label" sends the choice; the engine labels each object with its chosen mode
(``modes.scene_with_modes``)."""

from __future__ import annotations

import viser

from workbench.app.ui.run.modes import mode_option
from workbench.inference.answer.posterior import Posterior


class ModeChoice:
    """One dropdown per object of the frame, inside ``folder`` (shown while some object has another mode)."""

    def __init__(self, gui: viser.GuiApi, folder: viser.GuiFolderHandle):
        self.gui, self.folder = gui, folder
        self.dropdowns: list[viser.GuiDropdownHandle] = []
        self.iteration = -1  # the iteration whose posterior the dropdowns list

    def set_frame(self, names: list[str]) -> None:
        """A new frame: one hidden dropdown per object (``names``), nothing to choose yet."""
        for d in self.dropdowns:
            d.remove()
        with self.folder:
            self.dropdowns = [self.gui.add_dropdown(name, ("mode 1",), visible=False,
                                                    hint=f"the pose of {name} that \"Use best estimate as label\" "
                                                         "takes: the estimate (mode 1) or another mode, drawn as a "
                                                         "ghost in the 3D view")
                              for name in names]
        self.show(None, -1)

    def show(self, posterior: Posterior | None, iteration: int) -> None:
        """List ``posterior``'s modes (of the snapshot of ``iteration``; None: nothing to choose). A new
        posterior starts from its top mode: an earlier choice was among other poses."""
        if posterior is not None and iteration == self.iteration:
            return  # the same snapshot again (e.g. more particles drawn): keep the user's choice
        self.iteration = iteration if posterior is not None else -1
        objects = {o.obj: o for o in posterior.objects} if posterior is not None else {}
        for k, d in enumerate(self.dropdowns):
            o = objects.get(k)
            options = tuple(mode_option(j, o, m) for j, m in enumerate(o.modes)) if o is not None else ()
            if len(options) > 1:
                d.options = options
                d.value = options[0]
            d.visible = len(options) > 1
        self.folder.visible = any(d.visible for d in self.dropdowns)

    def chosen(self) -> tuple[tuple[int, ...], int]:
        """-> (per object the chosen mode's index, 0 for the estimate; the iteration they belong to)."""
        modes = []
        for d in self.dropdowns:
            options = tuple(d.options)
            modes.append(options.index(d.value) if d.visible and d.value in options else 0)
        return tuple(modes), self.iteration
