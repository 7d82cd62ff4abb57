"""The Data tab: which frame to load (a BOP dataset's scene and frame, or the demo), the frame's colour and depth
images, and where the evaluation runs. The Sequence folder sits in this tab too, between the buttons and the images
(``sequence.panel``, at ``sequence_order``)."""

from __future__ import annotations

import numpy as np
import viser

from workbench.app import protocol as p
from workbench.app.ui.widgets.colors import VIRIDIS, legend_html
from workbench.app.ui.widgets.numeric import NumberRule
from workbench.errors import InputError

# BOP names scenes and images by six-digit numbers.
SCENE_ID, FRAME_ID = NumberRule("Scene id", 0, 999_999, whole=True), NumberRule("Frame id", 0, 999_999, whole=True)


class DataTab:
    """The tab ``container``'s controls and images."""

    def __init__(self, gui: viser.GuiApi, container: viser.GuiTabHandle):
        with container:
            self.dataset = gui.add_text("Dataset", "", hint="a BOP dataset folder (root or split)")
            self.scene_id = gui.add_text("Scene id", "", hint="empty: the first scene")
            self.im_id = gui.add_text("Frame id", "", hint="empty: the first frame")
            self.load = gui.add_button("Load dataset", icon=viser.Icon.FOLDER_OPEN)
            self.demo = gui.add_button("Load demo", icon=viser.Icon.BOX, color="gray")
            # The colour image first, where the dataset has one: what poses are checked against by eye.
            self.rgb_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="colour image", format="jpeg",
                                           visible=False)
            self.depth_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="depth", format="png",
                                             visible=False)
            self.depth_legend = gui.add_html("")
            self.workers = gui.add_markdown("")
        # viser orders a container's elements by their ``order``: the Sequence folder, built later, goes here.
        self.sequence_order = (self.demo.order + self.rgb_image.order) / 2

    def frame_ids(self) -> tuple[int | None, int | None]:
        """The scene and frame typed (read by the panel's one rule for numbers); empty means the dataset's first."""
        out = []
        for handle, rule in ((self.scene_id, SCENE_ID), (self.im_id, FRAME_ID)):
            text = handle.value.strip()
            try:
                out.append(rule.parse(text) if text else None)
            except InputError as err:
                raise InputError(err.path, f"{err.problem} (or empty for the first)") from None
        return out[0], out[1]

    def show_frame(self, view: p.ObservationView) -> None:
        """A new frame: its images, and which frame it is (as the fields name it)."""
        self.depth_image.image = view.depth_image
        self.depth_image.visible = True
        lo, hi = view.depth_range
        self.depth_legend.content = legend_html("depth (m)", f"{lo:.2f}", f"{hi:.2f}", VIRIDIS,
                                                f"3D points: {view.color_legend}")
        if view.rgb_image is not None:
            self.rgb_image.image = view.rgb_image
        self.rgb_image.visible = view.rgb_image is not None
        if view.where is not None:
            self.dataset.value, self.scene_id.value, self.im_id.value = (view.where[0], str(view.where[1]),
                                                                         str(view.where[2]))

    def show_workers(self, pids: list[int], restarts: int) -> None:
        where = f"{len(pids)} worker processes" if pids else "in the estimator process"
        self.workers.content = f"Evaluation: {where}{f' · restarted {restarts}×' if restarts else ''}"
