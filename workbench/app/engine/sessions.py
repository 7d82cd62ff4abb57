"""Sessions on the engine's side: saving the run with its labels and its position in a sequence, and opening a saved
one: the file read and checked, and the frame and problem it continues rebuilt from its dataset, or the question to
ask first when that dataset changed since the save. Opening touches nothing of the current run, so a bad file leaves
it as it was; ``Engine.load_session`` then replaces it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from workbench.app import protocol as p
from workbench.errors import InputError
from workbench.sessions import store as sessions
from workbench.sessions.document import SessionState
from workbench.sessions.sequence_record import SequenceRecord, parse_record, record_json


@dataclass
class OpenedSession:
    """A session ready to continue. ``warnings``: what no longer matches the save, loaded anyway as the user
    confirmed; ``sequence``: its position in a sequence, if it was saved in one."""

    path: Path
    state: SessionState
    frame: object  # scene.Frame
    problem: object  # problem.Problem
    warnings: list[str]
    sequence: SequenceRecord | None = None

    @property
    def name(self) -> str:
        return self.path.name.removesuffix(".json")

    @property
    def config(self):
        """The panel's settings: in a sequence the sequence's (a tracked frame's run has its own), else the run's."""
        return self.state.estimator_config if self.sequence is None else self.sequence.config

    @property
    def dataset(self) -> Path:
        return Path(self.state.frame.dataset)

    def title(self) -> str:
        return f"session {self.name} · {self.dataset.name} · scene {self.frame.scene_id} · frame {self.frame.im_id}"


def open_session(path: Path, confirmed: bool) -> OpenedSession | p.SessionQuestion:
    """The session at ``path``, or the question to ask when its dataset changed and the user has not ``confirmed``
    loading it anyway. Raises InputError naming the file at fault."""
    state = sessions.load_session(path)
    record = None if state.sequence is None else parse_record(state.sequence, path, len(state.frame.object_ids),
                                                               state.frame.im_id)
    warnings = sessions.check_dataset(state)
    frame = problem = None
    if not warnings:
        frame, problem = sessions.session_problem(state)
        warnings = sessions.check_dataset(state, problem)
    if warnings and not confirmed:
        return p.SessionQuestion(path, warnings)
    if problem is None:
        frame, problem = sessions.session_problem(state)
    return OpenedSession(path, state, frame, problem, warnings, record)


def save_session(cmd: p.SaveSession, est, labels, evaluation: str, sequence: SequenceRecord | None = None
                 ) -> p.Saved:
    """Save ``est``'s run (None: nothing loaded) with ``labels`` (an ``engine_labels.FrameLabels``) and its place
    in a ``sequence`` where ``cmd`` says -> the message that tells the user; ``evaluation``: where the run was
    evaluated, for that message."""
    if est is None:
        raise InputError(None, "nothing is loaded: load a dataset or the demo first")
    if labels.frame_ref is None:
        raise InputError(None, f"this frame cannot be saved as a session: {labels.frame_ref_problem}")
    state = sessions.session_state_from(est, labels.frame_ref, labels.labels)
    state.sequence = None if sequence is None else record_json(sequence)
    path = sessions.save_session(Path(cmd.directory), cmd.name, state, overwrite=cmd.overwrite)
    n = sum(T is not None for T in labels.labels)
    where = "" if sequence is None else f"frame {sequence.current} of a sequence of {len(sequence.frames)}, "
    return p.Saved("session", str(path), f"{where}iteration {est.iteration}, {n} of {len(labels.labels)} objects "
                                         f"labelled, {evaluation} evaluation")
