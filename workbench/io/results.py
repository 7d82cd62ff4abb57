"""Results, in one place: the rows an estimate gives (``ResultRow``; ``ModeRow`` per mode of an object's posterior),
the BOP results CSV (``RESULTS_HEADER``, ``results_csv_lines``, ``read_results_csv``) and the files a run writes them
to (``ResultsFile`` for ``estimate --out``, ``PosteriorFile`` for ``--posterior``).

Results are written frame by frame as frames finish (``ResultsFile``, always sorted by frame whatever order they
finished in), so a crash or Ctrl-C loses at most the frames in progress, and ``--resume`` skips the frames already
written. ``check_results_out`` decides, before any work, whether the output path may be written: never inside a
dataset's scene or models folder, never over a file that is not a results CSV of ours unless forced.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from workbench.errors import InputError
from workbench.inference.answer.posterior import Posterior
from workbench.io import bop
from workbench.io.outputs import OutputLock, check_output_file, replace_file, write_file
from workbench.io.readers import parse_pose, read_json
from workbench.problem.problem import Problem
from workbench.problem.scene import Frame

# ----------------------------------------------------------------------------------------------------------------
# Rows


@dataclass
class ResultRow:
    """One estimate in the BOP results format. ``T_cam_obj``: (4, 4) metres; ``time``: seconds for the whole
    image (-1 when unknown)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    T_cam_obj: np.ndarray
    time: float


def result_rows(frame: Frame, problem: Problem, best: np.ndarray, scores: np.ndarray, seconds: float
                ) -> list[ResultRow]:
    """The best scene (K, 4, 4) in the table frame -> one BOP result row per object (camera frame)."""
    T_cam_obj = problem.camera.T_cam_world[None] @ best
    return [
        ResultRow(frame.scene_id, frame.im_id, m.obj_id, float(s), T, seconds)
        for m, s, T in zip(problem.models, scores, T_cam_obj)
    ]


@dataclass
class ModeRow(ResultRow):
    """A result row that is one mode of an object's posterior (``score`` its probability). The object's first row
    also carries the whole posterior of the object as ``posterior_record`` writes it (JSON-able), else None;
    ``posterior_seconds``: what the frame's posterior sweep took of its ``time``; ``cut_short``: the first stage the
    run's budget skipped (``Posterior.cut_short``), None where it finished."""

    posterior: dict | None = None
    posterior_seconds: float = 0.0
    cut_short: str | None = None


def posterior_rows(frame: Frame, problem: Problem, posterior: Posterior, seconds: float) -> list[ModeRow]:
    """Each object's modes as BOP result rows, best first, ``score`` = the mode's probability (camera frame): a
    reader that takes each object's top row gets the estimate."""
    rows = []
    for o, record in zip(posterior.objects, posterior_record(problem, posterior)):
        for i, mode in enumerate(o.modes):
            rows.append(ModeRow(frame.scene_id, frame.im_id, problem.models[o.obj].obj_id, mode.probability,
                                problem.camera.T_cam_world @ mode.T, seconds, record if i == 0 else None,
                                posterior.seconds, posterior.cut_short))
    return rows


def posterior_record(problem: Problem, posterior: Posterior) -> list[dict]:
    """Per object, its posterior in BOP's units and frame: each mode's pose in the camera frame (``R`` row-major,
    ``t`` mm), probability, log-likelihood and gap to the estimate (log-units) and what it is; the spread of its
    position (mm); the range of headings about the table's vertical (``vertical_cam``, a unit vector in the camera
    frame) that the view leaves open (degrees about the estimate's, or null); the share of its estimate's surface
    the sensor sees through, and the chance that it is none of the modes (``elsewhere``, beside the modes, whose
    probabilities sum to 1); for an object the sensor sees none of, its hiding region (``hiding``: the places its
    origin can be, camera frame mm, the estimate's first, with their probabilities and log-likelihood gaps to the
    estimate), else null."""
    T_cam_world = problem.camera.T_cam_world
    out = []
    for o in posterior.objects:
        model = problem.models[o.obj]
        modes = []
        for m in o.modes:
            T = T_cam_world @ m.T
            modes.append({"R": [round(float(v), 12) for v in T[:3, :3].ravel()],
                          "t": [round(1000.0 * float(v), 9) for v in T[:3, 3]],
                          "probability": round(m.probability, 6), "loglik": round(m.loglik, 3),
                          "gap": round(m.gap, 3), "what": m.what})
        out.append({"obj_id": model.obj_id, "name": model.name, "modes": modes,
                    "position_spread_mm": round(1000.0 * o.position_spread_m, 3),
                    "yaw_range_deg": None if o.yaw_range_deg is None else list(o.yaw_range_deg),
                    "seen_through": round(o.seen_through, 4), "elsewhere": round(o.elsewhere, 6),
                    "hiding": None if o.hiding is None else {
                        "places_mm": [[round(1000.0 * float(v), 3) for v in p] for p in
                                      o.hiding.places @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]],
                        "probabilities": [round(float(q), 6) for q in o.hiding.probabilities],
                        "gaps": [round(float(g), 3) for g in o.hiding.gaps]},
                    "vertical_cam": [round(float(v), 12) for v in T_cam_world[:3, 2]],
                    "temperature": posterior.temperature})
    return out


# ----------------------------------------------------------------------------------------------------------------
# The BOP results CSV


RESULTS_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]


def results_csv_lines(rows: list[ResultRow]) -> list[str]:
    """The data lines (no header, no newline) of a BOP results CSV: R 9 numbers row-major, t 3 numbers in mm,
    space-separated."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    for r in rows:
        R, t = bop.R_t_mm(r.T_cam_obj)
        w.writerow(
            [r.scene_id, r.im_id, r.obj_id, f"{r.score:.12g}", " ".join(f"{v:.12g}" for v in R),
             " ".join(f"{v:.12g}" for v in t), f"{r.time:.12g}"]
        )
    return buf.getvalue().splitlines()


def write_results_csv(path: Path, rows: list[ResultRow]) -> None:
    """BOP results CSV (``results_csv_lines`` under the header)."""
    write_results_lines(path, results_csv_lines(rows))


def write_results_lines(path: Path, lines: list[str]) -> None:
    """The header and ``lines`` (from ``results_csv_lines``), atomically."""
    replace_file(Path(path), "".join(f"{line}\n" for line in [",".join(RESULTS_HEADER), *lines]).encode())


def read_results_csv(path: Path) -> list[ResultRow]:
    """Inverse of ``write_results_csv``. A score or time that is not a finite number, and a line that repeats an
    earlier one, are refused naming the line: a score decides which row is an object's estimate, and NaN would make
    that depend on the rows' order; a repeated row would count one estimate twice."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "results file not found")
    try:
        lines = list(csv.reader(path.read_bytes().decode("utf-8").splitlines()))
    except UnicodeDecodeError as e:
        raise InputError(path, f"is not UTF-8 text ({e.reason} at byte {e.start}): not a results CSV") from None
    except csv.Error as e:
        raise InputError(path, f"is not a CSV ({e})") from None
    if not lines or [c.strip() for c in lines[0]] != RESULTS_HEADER:
        raise InputError(path, f"first line must be the header {','.join(RESULTS_HEADER)}")
    rows, first_seen = [], {}
    for n, cells in enumerate(lines[1:], start=2):
        if not cells:
            continue
        try:
            scene_id, im_id, obj_id, score, R, t, time = cells
            ids = (int(scene_id), int(im_id), int(obj_id))
            R, t = [float(v) for v in R.split()], [float(v) for v in t.split()]
            score, time = float(score), float(time)
        except ValueError as e:
            raise InputError(path, f"line {n} is not scene_id,im_id,obj_id,score,R,t,time: "
                                   f"{','.join(cells)[:120]!r}") from e
        if not (np.isfinite(score) and np.isfinite(time)):
            raise InputError(path, f"line {n}: score and time must be finite numbers, got score {cells[3]!r}, time "
                                   f"{cells[6]!r} ({','.join(cells)[:120]})")
        key = tuple(c.strip() for c in cells)
        if key in first_seen:
            raise InputError(path, f"line {n} repeats line {first_seen[key]} ({','.join(cells)[:120]}): one "
                                   "estimate would count twice; remove the copy")
        first_seen[key] = n
        rows.append(ResultRow(*ids, score, parse_pose(R, t, path, f"line {n}"), time))
    return rows


# ----------------------------------------------------------------------------------------------------------------
# The files a run writes


def check_results_out(out: Path, force: bool = False, resume: bool = False) -> list[str]:
    """Check, before any work, that ``estimate`` may write its results CSV at ``out`` -> the data lines already
    there to keep as they are (``resume``; else none). Refused with InputError: a folder, a path below a file, an
    unwritable place, anything inside a dataset's scene or models folder (even with ``force``), and an existing
    file that is not a results CSV of ours unless ``force``."""
    out = Path(out)
    if force and resume:
        raise InputError("--resume", "--resume keeps the results in --out and --force replaces the file: pass one")
    exists = check_output_file(out, ours=is_results_csv, force=force or resume,
                               what="a results CSV written by `workbench estimate`", flag="--out")
    if not exists:
        return []
    target = out.resolve()
    if not resume:
        return []
    text = target.read_text(encoding="utf-8", errors="replace")
    if text.startswith("\ufeff"):
        raise InputError(out, "starts with a UTF-8 byte order mark (BOM): it was saved by another program; remove "
                              "the BOM or start a new --out")
    if not text.startswith(",".join(RESULTS_HEADER)):
        raise InputError(out, "is not a results CSV written by `workbench estimate`: there is nothing to resume")
    try:
        read_results_csv(target)
    except InputError as err:
        raise InputError(out, f"cannot be resumed: {err.problem}. Its good lines are kept as they are; fix or "
                              "remove the bad line (e.g. one cut short when a run was killed), then --resume "
                              "again") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(out, f"is not a results CSV written by `workbench estimate` ({err}): there is nothing to "
                              "resume") from None
    return [line for line in text.splitlines()[1:] if line.strip()]


def check_resumed(results: "ResultsFile", dataset: Path, split: str | None = None) -> None:
    """The frames and objects already in a resumed results file are the dataset's: InputError naming the file when
    a row's frame is not in ``dataset`` or its object is not among its models (a CSV of another dataset)."""
    if not results.lines:
        return
    frames = set(bop.list_frames(dataset, split=split))
    models = bop.model_ids(dataset)
    for n, line in enumerate(results.lines, start=2):
        scene_id, im_id, obj_id = (int(v) for v in line.split(",", 3)[:3])
        if (scene_id, im_id) not in frames or obj_id not in models:
            what = (f"scene {scene_id} image {im_id}" if (scene_id, im_id) not in frames else f"object {obj_id}")
            raise InputError(results.path, f"line {n} holds {what}, which {dataset} does not have: these results "
                                           "were made on another dataset; choose another --out (the file was "
                                           "left as it is)")


def is_results_csv(path: Path) -> bool:
    """Whether ``path`` reads as a results CSV (InputError otherwise): the files `estimate` and `bench` may replace."""
    read_results_csv(path)
    return True


class ResultsFile:
    """The results CSV of a run, rewritten whole (atomically) after every frame: the file always holds every
    finished frame, in frame order, and nothing half-written. Lines kept from an earlier run (``lines``, checked
    by ``check_results_out``) stay exactly as they were."""

    def __init__(self, path: Path, lines: list[str] | None = None, lock: OutputLock | None = None):
        self.path = Path(path)
        self.lines = list(lines or [])
        self.lock = lock

    @classmethod
    def open(cls, path: Path, force: bool = False, resume: bool = False) -> "ResultsFile":
        """The results file of a run at ``path``, checked (``check_results_out``) and locked for this run
        (``io.outputs.OutputLock``: another run writing the same file is refused, naming its pid) until ``close``."""
        check_results_out(path, force=force, resume=resume)  # first: the folder exists and may be written
        lock = OutputLock(path).acquire()
        try:
            return cls(path, check_results_out(path, force=force, resume=resume), lock)  # as it is now, locked
        except BaseException:
            lock.release()
            raise

    def close(self) -> None:
        """Let other runs write the file."""
        if self.lock is not None:
            self.lock.release()

    @staticmethod
    def _frame(line: str) -> tuple[int, int]:
        scene_id, im_id = line.split(",", 2)[:2]
        return int(scene_id), int(im_id)

    def done(self) -> set[tuple[int, int]]:
        """(scene_id, im_id) of the frames already in the file."""
        return {self._frame(line) for line in self.lines}

    def add(self, rows: list[ResultRow]) -> None:
        lines = sorted(self.lines + results_csv_lines(rows), key=self._frame)
        write_file(self.path, "".join(f"{line}\n" for line in [",".join(RESULTS_HEADER), *lines]))
        self.lines = lines


POSTERIOR_KIND = "workbench-posterior"


class PosteriorFile:
    """``estimate --posterior``: per frame and object, the posterior (``posterior_record``) as JSON,
    rewritten whole after every frame like the results CSV, frames in order. Written only over a posterior file of
    ours (or with ``--force``); ``--resume`` keeps the frames already in it."""

    def __init__(self, path: Path, frames: dict[tuple[int, int], dict] | None = None,
                 lock: OutputLock | None = None):
        self.path = Path(path)
        self.frames = dict(frames or {})
        self.lock = lock

    @classmethod
    def open(cls, path: Path, force: bool = False, resume: bool = False) -> "PosteriorFile":
        """Checked before any work (``io.outputs.check_output_file``): InputError naming ``path`` where it may not be
        written, or, with ``resume``, where it is not a posterior file of ours. Locked for this run like the
        results CSV (another run writing the same file is refused, naming its pid) until ``close``."""
        cls._frames_kept(path, force, resume)  # first: the folder exists and may be written
        lock = OutputLock(path, flag="--posterior").acquire()
        try:
            return cls(path, cls._frames_kept(path, force, resume), lock)  # as it is now, locked
        except BaseException:
            lock.release()
            raise

    @staticmethod
    def _frames_kept(path: Path, force: bool, resume: bool) -> dict[tuple[int, int], dict]:
        exists = check_output_file(path, ours=_is_posterior_file, force=force or resume,
                                   what="a posterior JSON written by `workbench estimate`", flag="--posterior")
        if not (exists and resume):
            return {}
        if not _is_posterior_file(Path(path)):
            raise InputError(path, "is not a posterior JSON written by `workbench estimate`: there is nothing to "
                                   "resume; choose another --posterior")
        document = read_json(Path(path))
        return {(f["scene_id"], f["im_id"]): f for f in document["frames"]}

    def close(self) -> None:
        """Let other runs write the file."""
        if self.lock is not None:
            self.lock.release()

    def add(self, rows: list[ResultRow]) -> None:
        """The posteriors the frame's rows carry (``ModeRow``), with the frame's wall seconds, the posterior
        sweep's share of them and the stage a budget cut short (only where one did); nothing for rows without
        one."""
        records = [r.posterior for r in rows if getattr(r, "posterior", None) is not None]
        if not records:
            return
        scene_id, im_id = rows[0].scene_id, rows[0].im_id
        self.frames[(scene_id, im_id)] = {"scene_id": scene_id, "im_id": im_id, "seconds": round(rows[0].time, 3),
                                          "posterior_seconds": round(rows[0].posterior_seconds, 3),
                                          **({} if rows[0].cut_short is None else {"cut_short": rows[0].cut_short}),
                                          "objects": records}
        document = {"kind": POSTERIOR_KIND, "format_version": 1,
                    "frames": [frame for _, frame in sorted(self.frames.items())]}
        write_file(self.path, json.dumps(document, indent=1) + "\n")


def _is_posterior_file(path: Path) -> bool:
    try:
        document = read_json(path)
        return document.get("kind") == POSTERIOR_KIND and isinstance(document.get("frames"), list)
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return False
