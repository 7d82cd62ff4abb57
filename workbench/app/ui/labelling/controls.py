"""The Label tab's controls (``LabelTab``) and their layout; ``labelling.Labelling`` gives them their behaviour."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser

from workbench.app.ui.run.views import HEATMAP_MODES
from workbench.app.ui.widgets.numeric import NumberRule
from workbench.geometry import rot_x, rot_y, rot_z

# The pose fields' rules: a few metres hold any table scene; the angles' ranges are those ``matrix_to_euler``
# gives, so that a typed angle is shown back as typed.
POSITION_RULES = tuple(NumberRule(name, -500, 500, "cm") for name in ("x (cm)", "y (cm)", "z (cm)"))
ANGLE_RULES = (NumberRule("roll (°)", -180, 180, "°"), NumberRule("pitch (°)", -90, 90, "°"),
               NumberRule("yaw (°)", -180, 180, "°"))
NO_OBJECT = "(nothing loaded)"
TURNS = ("−90°", "+90°")
AXES = {"x": rot_x, "y": rot_y, "z": rot_z}  # the table's axes
# The object's own axis that goes down onto the table, as the "Lay on face" buttons name it.
FACES = {"−z": (0, 0, -1), "+z": (0, 0, 1), "−x": (-1, 0, 0), "+x": (1, 0, 0), "−y": (0, -1, 0), "+y": (0, 1, 0)}


@dataclass
class LabelTab:
    object: viser.GuiDropdownHandle
    state: viser.GuiMarkdownHandle
    # Text, not number inputs, read by ``pose_fields.PoseFields`` (see ``widgets.numeric`` for why).
    position: tuple[viser.GuiTextHandle, viser.GuiTextHandle, viser.GuiTextHandle]  # cm, table frame
    angles: tuple[viser.GuiTextHandle, viser.GuiTextHandle, viser.GuiTextHandle]  # roll, pitch, yaw (deg)
    turns: tuple[viser.GuiButtonGroupHandle, viser.GuiButtonGroupHandle, viser.GuiButtonGroupHandle]  # x, y, z
    lay: viser.GuiButtonGroupHandle
    show_gizmo: viser.GuiCheckboxHandle
    clear: viser.GuiButtonHandle
    modes: viser.GuiFolderHandle  # per object with other modes, which one "Use best estimate" takes (mode_choice)
    use_best: viser.GuiButtonHandle
    snap: viser.GuiButtonHandle
    fit: viser.GuiButtonHandle
    result: viser.GuiMarkdownHandle
    heatmap: viser.GuiDropdownHandle
    legend: viser.GuiHtmlHandle
    errors: viser.GuiMarkdownHandle
    overwrite_original: viser.GuiCheckboxHandle
    save: viser.GuiButtonHandle
    saved: viser.GuiMarkdownHandle
    backups: viser.GuiFolderHandle  # the scene_gt.json backups (``backups.Backups`` fills it)
    rgb_image: viser.GuiImageHandle  # what the labels are checked against by eye, where the dataset has one


def build_label_tab(gui: viser.GuiApi) -> LabelTab:
    obj = gui.add_dropdown("Object", (NO_OBJECT,), hint="the object whose label the fields and the gizmo edit")
    state = gui.add_markdown("")
    position = tuple(gui.add_text(r.label, r.show(0.0), hint="table frame: x, y along the table, z up from its "
                                  f"top; the object's origin; {r.span}") for r in POSITION_RULES)
    angles = tuple(gui.add_text(r.label, r.show(0.0), hint="about the table's axes: R = Rz(yaw) Ry(pitch) Rx(roll); "
                                f"{r.span}") for r in ANGLE_RULES)
    turns = tuple(gui.add_button_group(f"Turn about {a}", TURNS, hint=f"a quarter turn about the table's {a} axis, "
                                       "through the object's origin; it keeps its lowest point's height")
                  for a in AXES)
    lay = gui.add_button_group("Lay on face", tuple(FACES), hint="the object's own axis that goes down: it is "
                               "turned that way and put on the table where it is")
    # Off until the user labels: the gizmo would otherwise sit over the scene on every tab.
    show_gizmo = gui.add_checkbox("Gizmo", False, hint="drag the selected object in the 3D view; turns on when you "
                                  "choose an object or edit its pose")
    clear = gui.add_button("Clear label", icon=viser.Icon.ERASER, color="gray", hint="the selected object's")
    # Filled per object once the run has a posterior; hidden while no object has another mode.
    modes = gui.add_folder("Modes to label with", expand_by_default=True, visible=False)
    use_best = gui.add_button("Use best estimate as label", icon=viser.Icon.STAR,
                              hint="every object: the settled estimate, or the mode chosen above")
    snap = gui.add_button("Snap to plausible", icon=viser.Icon.ARROW_BAR_TO_DOWN,
                          hint="physics puts the labelled scene at rest (unlabelled objects: the best estimate)")
    fit = gui.add_button("Fit to depth", icon=viser.Icon.TARGET,
                         hint="local refinement of the labelled objects against the depth, then snap")
    result = gui.add_markdown("")
    heatmap = gui.add_dropdown("Label heatmap", ("off", *[m for m in HEATMAP_MODES if m != "off"]),
                               initial_value="off", hint="the labelled scene's fit per pixel, updated while you drag")
    legend = gui.add_html("")
    errors = gui.add_markdown("")
    overwrite_original = gui.add_checkbox("Overwrite scene_gt.json", False,
                                          hint="write into the dataset's own ground truth (a backup is kept); "
                                               "otherwise labels go to scene_gt_labels.json beside it")
    save = gui.add_button("Save labels", icon=viser.Icon.DEVICE_FLOPPY)
    saved = gui.add_markdown("")
    backups = gui.add_folder("scene_gt.json backups", expand_by_default=True)
    rgb_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="colour image", format="jpeg", visible=False)
    return LabelTab(object=obj, state=state, position=position, angles=angles, turns=turns, lay=lay,
                    show_gizmo=show_gizmo, clear=clear, modes=modes,
                    use_best=use_best, snap=snap, fit=fit, result=result, heatmap=heatmap, legend=legend,
                    errors=errors, overwrite_original=overwrite_original, save=save, saved=saved,
                    backups=backups, rgb_image=rgb_image)
