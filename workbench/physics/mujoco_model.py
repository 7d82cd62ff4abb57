"""The MuJoCo model the MuJoCo projector simulates in, written as MJCF from the same collision shapes, body frames,
table and ``PhysicsConfig`` as Bullet's world (``world.py``), so that both backends simulate the same scene.

What differs from Bullet, and why:

- The table is a thin fixed box, not a plane: a plane gives few contacts under a flat base and objects slide on it
  (mujoco issue #3524).
- MuJoCo mixes two geoms' frictions by their maximum; Bullet multiplies them, and its rolling and spinning frictions
  combine as r_a * f_b + r_b * f_a. Every pair of geoms that may touch (each object with the table, each pair of
  objects) is therefore an explicit contact pair carrying Bullet's combined values, and no geom collides otherwise.
- Bullet's damping removes a fraction of the speed per second; MuJoCo's joint damping is a force per speed. The
  free joints' damping is set per degree of freedom to mass (or principal moment) times the same rate
  (``dof_damping``), which removes the same fraction.
- Meshes (a convex hull, or each convex part of a compound) collide as their convex hulls in both; a compound's
  parts are padded as Bullet's are (``BULLET_COMPOUND_MARGIN``).
- ``sleep_calm``: Bullet's projector puts a calm body to sleep until a moving body touches it; MuJoCo's own sleeping
  does the same for a calm island of bodies (``dof_lengths``, ``SLEEP_SCALE``). Without it a body balanced on a
  point (a bottle on its cap: MuJoCo gives a convex mesh one contact there) topples in MuJoCo while Bullet freezes
  it, and resting scenes part by centimetres.

MuJoCo's quaternion order (w, x, y, z) is the project's own (``geometry``).
"""

from __future__ import annotations

import math

import numpy as np

from workbench.geometry import invert_pose, matrix_to_quat_wxyz
from workbench.physics.bodies import BodyFrame
from workbench.physics.collision import BOX, COMPOUND, CYLINDER, CollisionShape
from workbench.physics.config import PhysicsConfig
from workbench.problem.scene import ObjectModel, Table

TABLE_GEOM = "table"
# MuJoCo's sleep tolerance over Bullet's rest thresholds (``dof_lengths``). Measured on PI-PF's hypotheses of 6
# ycbv-real-dev frames (benchmarks/real_physics.py; MuJoCo against Bullet, mean model-point distance per object):
# 1.5 is as close as 1 or closer on every frame (median 0.65-1.5 mm; 1: 0.64-1.52 mm, frame 1/1 1.13 against
# 0.78 mm) and rests as soon or sooner; 2 is no closer. MuJoCo waits 10 calm steps and tests each speed component,
# where Bullet's projector waits 2 checks of 4 steps and tests the norms.
SLEEP_SCALE = 1.5
# Bullet's world sets its bodies' collision margin to 0, but a compound's pieces (read from an OBJ file) keep
# pybullet's default 1 mm: a compound rests 1 mm up in Bullet (a cup: 1.03 mm above its support points; a banana
# lying down, 1.8 mm). MuJoCo pads them as much, so that both rest such objects alike.
BULLET_COMPOUND_MARGIN = 1e-3


def _floats(values) -> str:
    """Numbers as MJCF writes them, exactly (17 significant digits)."""
    return " ".join(f"{float(v):.17g}" for v in np.ravel(values))


def body_geoms(k: int, shape: CollisionShape, frame: BodyFrame) -> tuple[list[str], list[str], list[str]]:
    """The geoms of body ``k`` in its body frame (``frame``, centre of mass and principal axes) -> (their names,
    MJCF ``<geom>`` elements, MJCF ``<mesh>`` assets they use). A box or cylinder is its own body frame
    (``bodies.body_frame``); a convex hull or a compound is one mesh geom per convex part, its vertices moved into
    the body frame."""
    T_body_shape = invert_pose(frame.T_obj_body) @ shape.T_obj_shape
    place = f'pos="{_floats(T_body_shape[:3, 3])}" quat="{_floats(matrix_to_quat_wxyz(T_body_shape[:3, :3]))}"'
    if shape.kind == BOX:
        return [f"b{k}g0"], [f'<geom name="b{k}g0" type="box" size="{_floats(shape.half_extents)}" {place}/>'], []
    if shape.kind == CYLINDER:  # MuJoCo's cylinder axis is its local z, as Bullet's
        size = _floats([shape.half_extents[0], shape.half_extents[2]])
        return [f"b{k}g0"], [f'<geom name="b{k}g0" type="cylinder" size="{size}" {place}/>'], []
    names, geoms, meshes = [], [], []
    for i, part in enumerate(shape.parts):
        local = part @ T_body_shape[:3, :3].T + T_body_shape[:3, 3]
        # inertia="shell": the mesh's own inertia is never used (the body's is given), and a flat V-HACD piece has
        # no volume, which MuJoCo's default inertia refuses.
        meshes.append(f'<mesh name="b{k}m{i}" vertex="{_floats(local)}" inertia="shell"/>')
        names.append(f"b{k}g{i}")
        geoms.append(f'<geom name="b{k}g{i}" type="mesh" mesh="b{k}m{i}"/>')
    return names, geoms, meshes


def contact_pair(geom1: str, geom2: str, friction1: float, friction2: float, config: PhysicsConfig,
                 table: bool, margin: float = 0.0) -> str:
    """An MJCF ``<pair>`` of two geoms with Bullet's combined frictions: sliding f1 * f2, rolling and spinning
    r * f2 + r * f1 (m), where the table (``table``: geom1 is the table) has no rolling or spinning friction of its
    own (as in ``world.World``): only the object's r times the table's f.
    Condim 6 (sliding, spinning, rolling) where either of the last two is on, else 3. ``margin`` (m): the two rest
    this far apart (MuJoCo's contact holds them at that distance), as Bullet's margins pad its shapes."""
    # geom1 is the table (friction1) or an object; geom2 always an object.
    weight = friction1 if table else friction1 + friction2
    spin, roll = config.spinning_friction * weight, config.rolling_friction * weight
    condim = 6 if spin > 0 or roll > 0 else 3
    friction = _floats([friction1 * friction2] * 2 + [spin, roll, roll])
    return (f'<pair geom1="{geom1}" geom2="{geom2}" condim="{condim}" friction="{friction}" '
            f'margin="{margin:.17g}"/>')


def _pad(shape: CollisionShape) -> float:
    """How far (m) Bullet's world pads ``shape``: the pieces of a compound by ``BULLET_COMPOUND_MARGIN``, nothing
    else."""
    return BULLET_COMPOUND_MARGIN if shape.kind == COMPOUND else 0.0


def build_mjcf(models: list[ObjectModel], table: Table, config: PhysicsConfig, shapes: list[CollisionShape],
               frames: list[BodyFrame], masses: list[float]) -> str:
    """The MJCF of the table (top at z = 0, ``config.table_thickness`` thick) and one free body per model, each
    colliding as its shape, with its mass (kg) and principal moments at its body frame. Bodies start at the origin;
    the projector places them."""
    cfg = config
    assets, bodies, pairs = [], [], []
    half = [(table.x_max - table.x_min) / 2, (table.y_max - table.y_min) / 2, cfg.table_thickness / 2]
    centre = [(table.x_min + table.x_max) / 2, (table.y_min + table.y_max) / 2, -half[2]]
    names = []
    for k, (model, shape, frame, mass) in enumerate(zip(models, shapes, frames, masses)):
        geom_names, geoms, meshes = body_geoms(k, shape, frame)
        assets += meshes
        names.append(geom_names)
        bodies.append(f'<body name="b{k}"><freejoint name="b{k}"/>'
                      f'<inertial pos="0 0 0" mass="{mass:.17g}" diaginertia="{_floats(frame.inertia)}"/>'
                      + "".join(geoms) + "</body>")
        pairs += [contact_pair(TABLE_GEOM, g, cfg.table_friction, model.friction, cfg, table=True,
                               margin=_pad(shape)) for g in names[k]]
        for j in range(k):
            pairs += [contact_pair(ga, gb, models[j].friction, model.friction, cfg, table=False,
                                   margin=_pad(shapes[j]) + _pad(shape))
                      for ga in names[j] for gb in names[k]]
    cone = "elliptic" if cfg.cone_friction else "pyramidal"
    sleep = "enable" if cfg.sleep_calm else "disable"
    return f"""<mujoco model="workbench">
  <compiler angle="radian" inertiafromgeom="false" autolimits="true"/>
  <option timestep="{cfg.timestep:.17g}" gravity="0 0 {-cfg.gravity:.17g}" iterations="{cfg.solver_iterations}"
          cone="{cone}" sleep_tolerance="{SLEEP_SCALE * cfg.rest_linear:.17g}">
    <flag autoreset="disable" sleep="{sleep}"/>
  </option>
  <default><geom contype="0" conaffinity="0"/></default>
  <asset>{"".join(assets)}</asset>
  <worldbody>
    <geom name="{TABLE_GEOM}" type="box" size="{_floats(half)}" pos="{_floats(centre)}"/>
    {"".join(bodies)}
  </worldbody>
  <contact>{"".join(pairs)}</contact>
</mujoco>"""


def dof_lengths(n_bodies: int, config: PhysicsConfig) -> np.ndarray:
    """The free joints' ``dof_length`` (6 K,) m that make MuJoCo's sleep test Bullet's rest test. MuJoCo lets a body
    sleep once every speed of its degrees of freedom times its length stays below ``sleep_tolerance`` for
    ``mjMINAWAKE`` (10) steps; with the tolerance ``SLEEP_SCALE`` times ``rest_linear`` (m/s), length 1 for the
    linear speeds and ``rest_linear / rest_angular`` (m) for the angular ones, that is each linear speed below
    ``SLEEP_SCALE * rest_linear`` and each angular speed below ``SLEEP_SCALE * rest_angular``."""
    return np.tile(np.r_[[1.0] * 3, [config.rest_linear / config.rest_angular] * 3], n_bodies)


def damping(frames: list[BodyFrame], masses: list[float], config: PhysicsConfig) -> np.ndarray:
    """The free joints' damping per degree of freedom (6 K,) for Bullet's damping: Bullet scales a speed by
    (1 - c) every second, i.e. dv/dt = ln(1 - c) v, which is MuJoCo's damping force -b v with b = -ln(1 - c) m for
    the linear speeds (N s/m) and -ln(1 - c) I_i for the angular ones about the principal axes (N m s/rad; a free
    joint's angular speeds are in the body frame)."""
    lin, ang = -math.log1p(-config.linear_damping), -math.log1p(-config.angular_damping)
    if not frames:
        return np.zeros(0)
    return np.concatenate([np.r_[[lin * m] * 3, ang * f.inertia] for f, m in zip(frames, masses)])
