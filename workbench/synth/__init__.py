"""Synthetic test scenes of the paper's cases and of real-like desks, written as a BOP dataset
(``workbench make-scenes``).

The paper's categories (Desingh et al. 2016, Sec. V), boxes on a bare 1.2 x 0.8 m table whose pose is given:
``touching`` (two boxes in face or edge contact), ``stacked`` (a smaller box resting on a larger one near its
edge), ``slant`` (a box leaning on another box and the table), ``occluded`` (a small box hidden behind a tall one),
``three`` and ``four`` (clutter mixing those relations).

Categories more like real frames (``DESKS``): ``clutter`` (4-6 objects, boxes with the can, the mug or both, some
touching, some stacked, the rest standing free, and 2-4 distractors; half the frames without the table pose) and
``mixed`` (2-3 objects mixing boxes with the can, the mug or both, 1-3 distractors, never the table pose). Their
desks are drawn from 0.9-2.4 x 0.7-1.5 m, often larger than the camera's view. *Distractors* are slabs (books),
cylinders (cups, bottles) and cables lying on the desk, clear of the objects: they are in the depth image but not
in scene_gt.json, from which the estimator learns which objects are present (scene_distractors.json lists them).
A frame without the table pose has no cam_R_w2c / cam_t_w2c in scene_camera.json, so the estimator must find the
table itself; the true pose is kept in scene_table.json. The can and the mug are meshes built here, watertight,
written with the boxes as BOP models (mm); the can is symmetric about its axis.

Categories for the posterior: ``handle_hidden`` and ``handle_shown`` (the mug and 0-2 boxes standing free, the
camera drawn about the mug's handle so that its body hides it, or so that it shows) and ``lying`` (2-4 objects
free, each in one of its stable poses). ``lying`` can draw from any BOP models (``make_scenes(models=...)``).

Categories of real shapes (``SHAPE_CATEGORIES``), drawn only from given models, which collide as V-HACD pieces:
``ycb_clutter`` (6-8 models, some touching, 2-4 distractors, other models among them), ``raised`` (2-4 models on a
large box on the table, which is environment: in the depth, not in scene_gt.json; no table pose), ``leaning`` (a
box leaning on a vessel or another box, 0-2 more) and ``tools`` (1-2 tools lying, 1-3 other models).

Every scene is laid out from *relations* (touch / stack / slant / hide / free), each new object moved along one
degree of freedom by bisection until it just touches its partner, then settled by physics in the generator's own
pybullet world (not ``workbench.physics``'s, whose V-HACD pieces it borrows for given models) and kept only when
the settled scene still is what its relations say (contacts from ``getContactPoints``, tilt, visibility);
otherwise the next random draw is tried.
Distractors are placed after settling, resting on the desk. Depth is ray-cast with open3d (independent of the
estimator's OpenGL renderer) and degraded by a Kinect-like sensor model.

In pipeline order:

- ``config``: the categories, their desks, and ``SynthConfig`` (how scenes are drawn, simulated, viewed, sensed);
- ``objects``: the boxes, the can and the mug, their meshes, and the geometry of resting and reaching;
- ``meshes``: the can, mug and cable meshes built here;
- ``sim``: the generator's pybullet world: settling, contacts, closest distances;
- ``layout``: objects placed by relations, per category, settled and checked;
- ``bodies``: given models as bodies of the generator's world, their V-HACD pieces at their centre of mass;
- ``roles``: what a given model can be in a scene (box, vessel, tool, other), from its geometry;
- ``resting``: given models placed on a surface (the table, a raised box): free, against another, leaning;
- ``shape_layouts``: the categories of real shapes, placed by ``resting``, settled and checked;
- ``distractors``: slabs, cylinders and cables on the desk;
- ``views``: the camera, ray-cast depth and object masks;
- ``sensor``: the Kinect-like depth noise;
- ``scenes``: one scene, drawn until its category holds and a camera shows it;
- ``dataset``: scenes written as a BOP dataset (``make_scenes``, ``make_demo``), and read back.

Callers import the generator's entry points from here: ``from workbench.synth import make_scenes``.
"""

from workbench.synth.config import CATEGORIES
from workbench.synth.dataset import frame_table_pose, load_distractors, make_demo, make_scenes, true_table_pose
from workbench.synth.views import visible_masks

__all__ = ["CATEGORIES", "frame_table_pose", "load_distractors", "make_demo", "make_scenes", "true_table_pose",
           "visible_masks"]
