"""Running an estimator over dataset frames, with a progress bar on stderr, and where its results may go.

Frames run one after another here (``--engine local``) or as Ray tasks over a cluster (``--engine ray``), both by
``run.frames.run_frames``. Results are written frame by frame as frames finish (``ResultsFile``, always sorted by frame
whatever order they finished in), so a crash or Ctrl-C loses at most the frames in progress, and ``--resume`` skips
the frames already written. ``check_results_out`` decides, before any work, whether the output path may be written:
never inside a dataset's scene or models folder, never over a file that is not a results CSV of ours unless forced.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from workbench.checks import check_workers
from workbench.errors import InputError
from workbench.evaluation import ChunkedEvaluator, Evaluator, WorkerCrashed, make_evaluator
from workbench.evaluation.local import prepare_meshes
from workbench.evaluation.ray import RayConfig  # imports Ray only when used
from workbench.inference.config import EstimatorConfig
from workbench.inference.estimator import Estimator, object_confidence
from workbench.io import bop
from workbench.io.bop import ResultRow
from workbench.io.outputs import OutputLock, check_output_file, write_file
from workbench.meshes.heavy import announced_if, heavy_models
from workbench.problem.build import load_bop_problem, posterior_rows, result_rows
from workbench.problem.problem import Problem, ProblemConfig
from workbench.problem.scene import Frame
from workbench.run.frames import FrameFailure, FrameKey, run_frames

# Where stderr is not a terminal (a log file), a frame's progress is one line at most this often (s): a six-object
# frame takes about a minute, and a log that says nothing for that long looks stuck.
LOG_EVERY_S = 10.0


def estimate_frame(
    dataset: Path,
    scene_id: int,
    im_id: int,
    config: EstimatorConfig,
    problem_config: ProblemConfig,
    evaluator_for: Callable[[Problem], Evaluator],
    split: str | None = None,
    object_ids: list[int] | None = None,
    early_stop: bool = True,
    show_progress: bool = False,
) -> list[ResultRow]:
    """Estimate one frame with the evaluator ``evaluator_for(problem)`` (closed afterwards) -> its BOP result rows,
    ``time`` the frame's wall seconds: each object's modes, best first, with their probabilities
    (``problem.build.posterior_rows``; one row per object, scored by ``object_confidence``, where the search gives no
    posterior). What the view leaves open is said in one line on stderr (``Posterior.summary``).
    ``show_progress``: a progress bar of its iterations on stderr when stderr is a terminal, opened once the frame
    has loaded (a bad frame fails before any bar)."""
    t0 = time.perf_counter()
    frame, problem = load_bop_problem(dataset, scene_id, im_id, split, object_ids, problem_config)
    # A frame with a model of over heavy.HEAVY_FACES faces says what it does while it does it: simplifying the model
    # (once: cached), starting the workers (each takes the whole model) and estimating (on a terminal, its bar).
    heavy = heavy_models(problem.models)
    if heavy:
        prepare_meshes(problem)  # announced on its own; the evaluators then read the cache
    with announced_if(heavy, f"starting the evaluation of scene {scene_id} frame {im_id}"):
        evaluator = evaluator_for(problem)
    try:
        with announced_if(heavy if not (show_progress and sys.stderr.isatty()) else "",
                          f"estimating scene {scene_id} frame {im_id}"):
            estimator, best = run_estimator(Estimator(problem, config, evaluator), f"scene {scene_id} frame {im_id}",
                                            early_stop, show_progress)
    finally:
        evaluator.close()
    if estimator.posterior is not None:  # one line per frame: what the view leaves open
        print(f"scene {scene_id} frame {im_id}: {estimator.posterior.summary(problem)} "
              f"[posterior {estimator.posterior.seconds:.1f} s]", file=sys.stderr)
    return estimator_rows(frame, problem, estimator, best, time.perf_counter() - t0)


def run_estimator(estimator: Estimator, desc: str, early_stop: bool = True, show_progress: bool = False
                  ) -> tuple[Estimator, np.ndarray]:
    """Run ``estimator`` to its iteration budget (or convergence, ``early_stop``) -> (it, its settled estimate
    (K, 4, 4) table frame). ``show_progress``: a progress bar named ``desc`` on stderr when stderr is a terminal."""
    # On a terminal only (disable=None): in a log file the bar's carriage returns would share lines with the
    # messages after it, so there a plain line says how far the frame is, at most every LOG_EVERY_S seconds.
    t0 = last = time.perf_counter()
    done = 0
    with tqdm(total=estimator.config.iterations + 1, desc=desc, file=sys.stderr, leave=False,
              disable=None if show_progress else True) as bar:
        def progress(report):
            nonlocal last, done
            done += 1
            bar.update(1)
            bar.set_postfix(best=f"{report.best_loglik:.0f}", ess=f"{report.ess:.0f}")
            now = time.perf_counter()
            if show_progress and bar.disable and now - last >= LOG_EVERY_S:
                last = now
                print(f"{desc}: step {done} of at most {bar.total} after {now - t0:.0f} s "
                      f"(best {report.best_loglik:.0f})", file=sys.stderr, flush=True)
        best = estimator.run(stop_on_convergence=early_stop, callback=progress)
    return estimator, best


def estimator_rows(frame: Frame, problem: Problem, estimator: Estimator, best: np.ndarray, seconds: float
                   ) -> list[ResultRow]:
    """A finished estimator's BOP result rows, ``time`` = ``seconds``: each object's modes, best first, with their
    probabilities (``problem.build.posterior_rows``); one row per object, scored by ``object_confidence``, where the
    search gives no posterior."""
    if estimator.posterior is not None:
        return posterior_rows(frame, problem, estimator.posterior, seconds)
    scores = object_confidence(problem, estimator.particles.projected, estimator.weights(), best)
    return result_rows(frame, problem, best, scores, seconds)


def estimate_frame_task(scene_id: int, im_id: int, dataset: Path, config: EstimatorConfig,
                        problem_config: ProblemConfig, workers: int, split: str | None,
                        object_ids: list[int] | None, early_stop: bool) -> list[ResultRow]:
    """One frame as a Ray task, on one CPU: its batches split as ``workers`` local processes would split them
    (``ChunkedEvaluator``), so that its rows equal those of `--engine local` with the same ``workers``."""
    # One llvmpipe thread, as in a local pool's workers: the other tasks keep the other cores busy.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    return estimate_frame(dataset, scene_id, im_id, config, problem_config,
                          lambda problem: ChunkedEvaluator(problem, workers), split, object_ids, early_stop)


def estimate_frames(
    dataset: Path,
    frames: list[tuple[int, int]],
    config: EstimatorConfig,
    problem_config: ProblemConfig,
    workers: int,
    split: str | None = None,
    object_ids: list[int] | None = None,
    early_stop: bool = True,
    on_frame: Callable[[list[ResultRow]], None] | None = None,
    ray: RayConfig | None = None,
    on_failure: Callable[[FrameFailure], None] | None = None,
    max_retries: int = 3,
) -> list[ResultRow]:
    """Estimate every (scene_id, im_id) frame -> BOP result rows, in the order the frames finished.
    ``on_frame(rows)`` gets each frame's rows as soon as it is done (to write them).

    Locally (``ray`` None) frames run one after another, each on a worker pool of its own (the problem, hence the
    renderer's camera and the physics table, differs per frame), and the first bad frame raises. With ``ray`` (a
    RayConfig) every frame is a Ray task (``estimate_frame_task``); a frame that fails goes to ``on_failure`` (if
    None: raised as InputError once the others are done) and the others go on. Locally, a dead evaluation worker
    is started again and its part of the batch retried, up to ``max_retries`` times per batch (then InputError)."""
    config.validate()  # before any file is read or worker started
    check_workers(workers)
    rows: list[ResultRow] = []
    failures: list[FrameFailure] = []

    def done(_frame: FrameKey, frame_rows: list[ResultRow]) -> None:
        if on_frame is not None:
            on_frame(frame_rows)
        rows.extend(frame_rows)

    def here(scene_id: int, im_id: int) -> list[ResultRow]:
        try:
            return estimate_frame(dataset, scene_id, im_id, config, problem_config,
                                  lambda problem: make_evaluator(problem, workers, max_retries=max_retries), split,
                                  object_ids, early_stop, show_progress=True)
        except WorkerCrashed as err:
            raise InputError(f"scene {scene_id} frame {im_id}",
                             f"{err}; the frames before it are kept (run again with --resume)") from None

    run_frames(frames, here, estimate_frame_task,
               (Path(dataset).resolve(), config, problem_config, workers, split, object_ids, early_stop),
               ray, done, on_failure or failures.append)
    if failures:
        raise InputError(dataset, "; ".join(f"scene {f.frame[0]} frame {f.frame[1]}: {f.problem}"
                                            for f in failures))
    return rows


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
    if not text.startswith(",".join(bop.RESULTS_HEADER)):
        raise InputError(out, "is not a results CSV written by `workbench estimate`: there is nothing to resume")
    try:
        bop.read_results_csv(target)
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
    bop.read_results_csv(path)
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
        lines = sorted(self.lines + bop.results_csv_lines(rows), key=self._frame)
        write_file(self.path, "".join(f"{line}\n" for line in [",".join(bop.RESULTS_HEADER), *lines]))
        self.lines = lines


POSTERIOR_KIND = "workbench-posterior"


class PosteriorFile:
    """``estimate --posterior``: per frame and object, the posterior (``problem.build.posterior_record``) as JSON,
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
        document = json.loads(Path(path).read_text(encoding="utf-8"))
        return {(f["scene_id"], f["im_id"]): f for f in document["frames"]}

    def close(self) -> None:
        """Let other runs write the file."""
        if self.lock is not None:
            self.lock.release()

    def add(self, rows: list[ResultRow]) -> None:
        """The posteriors the frame's rows carry (``problem.build.ModeRow``), with the frame's wall seconds and the
        posterior sweep's share of them; nothing for rows without one."""
        records = [r.posterior for r in rows if getattr(r, "posterior", None) is not None]
        if not records:
            return
        scene_id, im_id = rows[0].scene_id, rows[0].im_id
        self.frames[(scene_id, im_id)] = {"scene_id": scene_id, "im_id": im_id, "seconds": round(rows[0].time, 3),
                                          "posterior_seconds": round(rows[0].posterior_seconds, 3),
                                          "objects": records}
        document = {"kind": POSTERIOR_KIND, "format_version": 1,
                    "frames": [frame for _, frame in sorted(self.frames.items())]}
        write_file(self.path, json.dumps(document, indent=1) + "\n")


def _is_posterior_file(path: Path) -> bool:
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
        return document.get("kind") == POSTERIOR_KIND and isinstance(document.get("frames"), list)
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return False
