"""The scene generator behind ``workbench make-scenes``: synthetic depth frames of the paper's cases and of
real-like desks, written as a BOP dataset.

- ``scenes``: the categories, layouts settled in the generator's own pybullet world, distractors, ray-cast depth
  and BOP writing;
- ``meshes``: the can, mug and cable meshes it builds;
- ``sensor``: its Kinect-like depth noise.

Callers import the generator's entry points from here: ``from workbench.synth import make_scenes``.
"""

from workbench.synth.scenes import (
    CATEGORIES, frame_table_pose, load_distractors, make_demo, make_scenes, true_table_pose, visible_masks,
)

__all__ = ["CATEGORIES", "frame_table_pose", "load_distractors", "make_demo", "make_scenes", "true_table_pose",
           "visible_masks"]
