"""Nothing lost, nothing stuck (issue 34), the parts that need no physics, rendering, Ray or a browser: damaged
caches rebuilt, results files locked and guarded, every output a command writes checked, a dead evaluation worker
restarted with its batch retried."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from workbench import cache


# ----------------------------------------------------------------------------------------------------------------
# Caches: verified on read, rebuilt with a warning naming the file

DAMAGE = {
    "emptied": lambda p: p.write_bytes(b""),
    "truncated": lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]),
    "garbage": lambda p: p.write_bytes(b"not a zip file at all" * 10),
    "one byte flipped": lambda p: p.write_bytes(_flip(p.read_bytes())),
    "no checksum": lambda p: np.savez(open(p, "wb"), vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]])),
    "folder": lambda p: (p.unlink(), p.mkdir()),
}


def _flip(data: bytes) -> bytes:
    # a byte inside the stored arrays (uncompressed npz: the data lies after the member headers)
    i = len(data) // 3
    return data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:]


def _collision_shape():
    from workbench.physics.collision import BOX, CollisionShape

    return CollisionShape(BOX, np.eye(4), np.array([0.05, 0.03, 0.02]), (), 0.9, 0.004)


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_collision_cache_file_is_named_and_rebuilt(damage, tmp_path, caplog):
    from workbench.physics import collision

    builds = []

    def compute():
        builds.append(1)
        return _collision_shape()

    collision._cached("k" * 40, tmp_path, compute)
    path = tmp_path / ("k" * 40 + ".npz")
    assert path.is_file() and builds == [1]
    collision._MEMORY_CACHE.clear()
    DAMAGE[damage](path)
    with caplog.at_level(logging.WARNING):
        shape = collision._cached("k" * 40, tmp_path, compute)
    assert builds == [1, 1] and shape.kind == "box"
    assert str(path) in caplog.text and "rebuilding" in caplog.text
    collision._MEMORY_CACHE.clear()
    caplog.clear()
    collision._cached("k" * 40, tmp_path, compute)  # rebuilt for good: read back without a warning
    assert builds == [1, 1] and not caplog.text
    collision._MEMORY_CACHE.clear()


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_render_cache_file_is_named_and_rebuilt(damage, tmp_path, caplog, monkeypatch):
    from workbench.render import depth

    builds = []

    def decimate(mesh, max_error):
        builds.append(1)
        return trimesh.creation.icosphere(1)

    monkeypatch.setattr(depth, "_decimate_within", decimate)
    mesh = trimesh.creation.icosphere(4)
    depth.render_mesh(mesh, cache_dir=tmp_path)
    (path,) = tmp_path.glob("*.npz")
    depth._MESH_CACHE.clear()
    DAMAGE[damage](path)
    with caplog.at_level(logging.WARNING):
        simple = depth.render_mesh(mesh, cache_dir=tmp_path)
    assert builds == [1, 1] and len(simple.faces) == 80
    assert str(path) in caplog.text and "rebuilding" in caplog.text
    depth._MESH_CACHE.clear()


def test_a_cache_that_cannot_be_written_is_a_warning_not_an_error(tmp_path, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with caplog.at_level(logging.WARNING):
        cache.save(blocker / "below" / "a.npz", {"a": np.zeros(3)})
    assert "could not write the cache file" in caplog.text
