"""Milliseconds per particle of the batched depth renderer: B particles of 2 and 4 boxes on a table, 160x120 ROI.

Each backend runs in its own spawned process (the GL backend is fixed per process). Usage:
    PYTHONPATH=. python benchmarks/render_speed.py [--particles 700] [--repeats 5]
"""

from __future__ import annotations

import argparse
import multiprocessing
import time

import numpy as np
import trimesh

from workbench.geometry import invert_pose, make_pose, pose_from_xyz_rpy
from workbench.problem.scene import Camera
from workbench.render.depth import BACKENDS, DepthRenderer, RenderConfig


def roi_camera() -> Camera:
    """A 640x480 Kinect-like camera 0.8 m from the table centre at 45 deg, cropped to the central 320x240 and
    halved: 160x120."""
    eye, target = np.array([0.0, -0.57, 0.57]), np.zeros(3)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T_cam_world = invert_pose(make_pose(np.stack([x, np.cross(z, x), z], axis=1), eye))
    K = np.array([[570.0, 0.0, 319.5], [0.0, 570.0, 239.5], [0.0, 0.0, 1.0]])
    return Camera(K, 640, 480, T_cam_world).cropped(160, 120, 320, 240).scaled(0.5)


def particles(rng: np.random.Generator, n: int, extents: np.ndarray) -> np.ndarray:
    """Boxes lying flat at random places and yaws within 10 cm of the table centre. -> (n, k, 4, 4)."""
    k = len(extents)
    xyz_rpy = np.zeros((n, k, 6))
    xyz_rpy[..., :2] = rng.uniform(-0.1, 0.1, size=(n, k, 2))
    xyz_rpy[..., 2] = extents[:, 2] / 2
    xyz_rpy[..., 5] = rng.uniform(-np.pi, np.pi, size=(n, k))
    return pose_from_xyz_rpy(xyz_rpy)


def measure(backend: str, n_boxes: int, n_particles: int, repeats: int) -> tuple[float, float, float]:
    """-> (ms per particle in a batch, ms for a batch of one, fraction of ROI pixels covered)."""
    rng = np.random.default_rng(0)
    extents = rng.uniform([0.04, 0.04, 0.03], [0.12, 0.08, 0.08], size=(n_boxes, 3))
    meshes = [trimesh.creation.box(e) for e in extents]
    poses = particles(rng, n_particles, extents)
    with DepthRenderer(roi_camera(), meshes, RenderConfig(backend=backend)) as renderer:
        depth = renderer.render(poses)  # warm-up: shader JIT, framebuffer allocation
        batch, single = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            renderer.render(poses)
            batch.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            renderer.render(poses[:1])
            single.append(time.perf_counter() - t0)
    return 1e3 * np.median(batch) / n_particles, 1e3 * np.median(single), float(np.mean(depth > 0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=700)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(f"{'backend':8} {'boxes':>5} {'ms/particle':>12} {'1-particle ms':>14} {'coverage':>9}")
    for backend in BACKENDS:
        with multiprocessing.get_context("spawn").Pool(1) as pool:
            for n_boxes in (2, 4):
                try:
                    per, one, cover = pool.apply(measure, (backend, n_boxes, args.particles, args.repeats))
                except RuntimeError as e:
                    print(f"{backend:8} unavailable: {e}")
                    break
                print(f"{backend:8} {n_boxes:5d} {per:12.3f} {one:14.2f} {cover:9.1%}")


if __name__ == "__main__":
    main()
