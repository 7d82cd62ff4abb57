"""What the browser server and the estimator process say to each other over their two queues.

Commands go one way (server -> engine), messages the other (engine -> server). Everything is a small picklable
dataclass of numpy arrays and numbers: the engine downsamples before it sends (the top particles, one chosen
particle's heatmap), so a message costs at most a few hundred kilobytes whatever the particle count.
Poses are 4x4 float arrays in the table frame; conversion to viser's (wxyz, position) happens in the views.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from workbench.inference.answer.posterior import Posterior
from workbench.inference.config import EstimatorConfig


@dataclass(frozen=True)
class Source:
    """Which frame to estimate: a BOP dataset (root or split folder) and a frame, or the bundled demo.
    ``scene_id``/``im_id`` None mean the dataset's first frame."""

    dataset: Path | None = None
    scene_id: int | None = None
    im_id: int | None = None
    demo: bool = False

    def describe(self) -> str:
        if self.demo:
            return "demo"
        scene = "its first scene" if self.scene_id is None else f"scene {self.scene_id}"
        frame = "first frame" if self.im_id is None else f"frame {self.im_id}"
        return f"{self.dataset} {scene}, {frame}"

    def title(self, scene_id: int, im_id: int) -> str:
        """The loaded frame ``im_id`` of scene ``scene_id`` as the panel's title names it."""
        name = "demo" if self.demo else Path(self.dataset).name
        return f"{name} · scene {scene_id} · frame {im_id}"


# ---------------------------------------------------------------------------------------------------------------
# Commands: server -> engine


@dataclass(frozen=True)
class Load:
    """Load a frame and start a fresh run on it; on failure the current problem and run are kept."""

    source: Source
    config: EstimatorConfig
    likelihood: str


@dataclass(frozen=True)
class Step:
    """One iteration (also while paused)."""


@dataclass(frozen=True)
class Run:
    """Step until the iteration budget, convergence (if ``stop_on_convergence``) or a Pause."""

    stop_on_convergence: bool = True


@dataclass(frozen=True)
class Pause:
    """Stop running after the iteration in progress."""


@dataclass(frozen=True)
class Shown:
    """The server has taken in the snapshot of ``iteration``. A running engine starts the next iteration only
    once the last one it published is shown, so the display never falls behind the run, and a Pause pressed
    while iteration k is on display stops the run at k + 1 at the latest."""

    iteration: int


@dataclass(frozen=True)
class Reset:
    """Throw the particles away and start again (seed and likelihood model take effect here)."""

    config: EstimatorConfig
    likelihood: str


@dataclass(frozen=True)
class SetConfig:
    """New particle count, Sigma, method or iteration budget, from the next step on; the run is kept."""

    config: EstimatorConfig


@dataclass(frozen=True)
class Select:
    """Explain the particle at ``rank`` (0 = most likely) of the last published ordering."""

    rank: int


@dataclass(frozen=True)
class SetDisplay:
    """How many particles (most likely first) each snapshot carries."""

    max_particles: int


@dataclass(frozen=True)
class Shutdown:
    pass


# Labelling and sessions. Labels are per object a (4, 4) T_world_obj in the table frame, or None (not labelled).


@dataclass(frozen=True)
class SetLabels:
    """The labels as the panel now shows them (sent on every edit and gizmo move). The engine keeps only the
    latest: its heatmap and error work runs once the queue is drained, so stale edits are dropped, not queued up.
    ``heatmap``: whether to render the labelled scene's per-pixel fit."""

    labels: tuple
    heatmap: bool = False


@dataclass(frozen=True)
class SnapLabels:
    """Let physics put the labelled scene at rest (unlabelled objects: the best estimate)."""


@dataclass(frozen=True)
class FitLabels:
    """Refine the labelled objects against the depth (local search), then snap."""


@dataclass(frozen=True)
class UseBestAsLabel:
    """Label every object with the most likely scene, settled. ``modes``: per object the index of the mode to use
    instead (0: the estimate), of the posterior the server showed with the snapshot of ``iteration``; ignored when
    the engine's posterior is of another iteration."""

    modes: tuple[int, ...] = ()
    iteration: int = -1


@dataclass(frozen=True)
class SaveLabels:
    """Write the labels to scene_gt_labels.json, or with ``overwrite_original`` (an explicit user choice) into the
    dataset's scene_gt.json after a backup."""

    overwrite_original: bool = False


@dataclass(frozen=True)
class ListBackups:
    """List the backups of the loaded frame's scene_gt.json (``Backups``), as saving with ``overwrite_original``
    keeps them."""


@dataclass(frozen=True)
class RestoreBackup:
    """Put the backup ``name`` (a file name ``Backups`` listed) back as the scene's scene_gt.json, the current one
    backed up first. The server sends it only once the user confirmed."""

    name: str


@dataclass(frozen=True)
class SaveSession:
    directory: Path
    name: str
    overwrite: bool = False


@dataclass(frozen=True)
class LoadSession:
    """Continue a saved session. Without ``confirmed``, dataset files that changed since the save make the engine
    ask (``SessionQuestion``) instead of loading."""

    path: Path
    confirmed: bool = False


# Sequences: the frames of the loaded frame's scene, one after another (``engine_sequence``).


@dataclass(frozen=True)
class NextFrame:
    """Go to the scene's frame after the one on show: tracked from the run on show (the frames processed after
    the one on show are dropped from the timeline), or, where that run has not changed since its next frame was
    tracked from it, that frame as it was."""


@dataclass(frozen=True)
class ShowFrame:
    """Show the processed frame ``im_id`` of the sequence again, its run as it was left (nothing is re-run)."""

    im_id: int


# Sequence labels: one label per object for the whole sequence, checked against every frame's depth
# (``engine.label_sequence``). Object ``index``es are positions in the frames' object list.


@dataclass(frozen=True)
class CheckSequenceLabels:
    """Start the sequence's labels and check every frame: from the Label tab's labels on the frame on show
    (``start`` "current", every object labelled), carried by each frame's camera pose, or from the labels saved
    before (``start`` "saved", scene_gt_labels.json); ``frames``: "A:B" (image ids, inclusive), "" for all."""

    start: str = "current"
    frames: str = ""


@dataclass(frozen=True)
class PropagateLabel:
    """Object ``index``'s label on the frame on show becomes its pose on every frame of the sequence, or
    (``from_here``) from this frame on; every frame is checked again."""

    index: int
    from_here: bool = False


@dataclass(frozen=True)
class EndSequenceLabel:
    """Object ``index``'s label ends on frame ``last`` (it was taken out after it); every frame checked again."""

    index: int
    last: int


@dataclass(frozen=True)
class FitSequenceLabels:
    """Fit the still labels to a spread of the frames at once, snap them with physics and fit again; re-check."""


@dataclass(frozen=True)
class SaveSequenceLabels:
    """Write the sequence's labels (scene_gt_labels.json, its info and provenance files), or with
    ``overwrite_original`` the scene's own scene_gt.json and scene_gt_info.json after backups."""

    overwrite_original: bool = False


@dataclass(frozen=True)
class ShowLabelledFrame:
    """Show frame ``im_id`` of the sequence's labels: its run where it was processed, else the frame with a fresh
    run, its labels those of the sequence."""

    im_id: int


Command = (Load | Step | Run | Pause | Shown | Reset | SetConfig | Select | SetDisplay | Shutdown | SetLabels
           | SnapLabels | FitLabels | UseBestAsLabel | SaveLabels | ListBackups | RestoreBackup | SaveSession
           | LoadSession | NextFrame | ShowFrame | CheckSequenceLabels | PropagateLabel
           | EndSequenceLabel | FitSequenceLabels | SaveSequenceLabels | ShowLabelledFrame)


# ---------------------------------------------------------------------------------------------------------------
# Messages: engine -> server


@dataclass
class MeshData:
    name: str
    vertices: np.ndarray  # (V, 3) float32, object frame, metres
    faces: np.ndarray  # (F, 3) int32
    # (E, 2, 3) float32, object frame: the outline drawn for ground truth, labels and modes (the feature edges
    # of a coarse decimation, see observation.outline_edges); None: every triangle edge
    edges: np.ndarray | None = None
    # The same, coarser, for the particles, drawn by the dozen per object: None: ``edges``
    cloud_edges: np.ndarray | None = None
    # What a solid object is drawn with (the estimate, a chosen particle after physics): a decimation to at most
    # observation.SOLID_FACES faces, (vertices (V', 3) float32, faces (F', 3) int32); None: vertices and faces
    solid: tuple[np.ndarray, np.ndarray] | None = None

    def solid_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        return self.solid if self.solid is not None else (self.vertices, self.faces)


@dataclass
class PointSet:
    """Observed points drawn as one cloud: (P, 3) float32 table frame, (P, 3) uint8 colours, and the points'
    diameter (m), the spacing of the pixels they were sampled from at the frame's median depth."""

    points: np.ndarray
    colors: np.ndarray
    point_size: float


@dataclass
class ObservationView:
    """Everything static about the loaded frame, in the table frame.

    ``near``/``far``: the depth frame as points, finely sampled around the objects and coarsely elsewhere (the
    rest of the table and the background only give context); ``grid_points``: the observed points of the
    problem's pixel grid where ``grid_mask`` (h, w) is true, in row-major order, onto which heatmaps go."""

    title: str
    near: PointSet
    far: PointSet
    color_legend: str  # what the clouds' colours mean
    depth_image: np.ndarray  # (H', W', 3) uint8, coloured depth for the panel
    depth_range: tuple[float, float]  # metres, the depth image's colour scale
    table: tuple[float, float, float, float]  # x_min, x_max, y_min, y_max
    region: tuple[float, float, float, float]  # the object region: x_min, x_max, y_min, y_max
    meshes: list[MeshData]
    T_world_cam: np.ndarray  # (4, 4)
    K: np.ndarray  # (3, 3)
    image_size: tuple[int, int]  # width, height
    grid_points: np.ndarray  # (G, 3) float32
    grid_point_size: float  # m: the grid's pixel spacing at the median depth
    grid_mask: np.ndarray  # (h, w) bool
    gt_T_world_obj: np.ndarray | None  # (K, 4, 4), NaN rows where unknown; None without ground truth
    rgb_image: np.ndarray | None = None  # (H', W', 3) uint8, the frame's colour image for the panel, if it has one
    where: tuple[str, int, int] | None = None  # (dataset folder, scene id, frame id), for the Data tab's fields


@dataclass
class ParticleCloud:
    """The ``M`` most likely particles after an iteration, ordered by weight (rank 0 first)."""

    iteration: int
    n_total: int
    poses: np.ndarray  # (M, K, 4, 4) float32, projected (after physics)
    weights: np.ndarray  # (M,) normalised over all N particles
    loglik: np.ndarray  # (M,)
    status: np.ndarray  # (M,) physics status codes


@dataclass
class Snapshot:
    """Published after every iteration: the report, the particle cloud and whether the engine keeps running."""

    report: dict  # IterationReport.as_dict()
    cloud: ParticleCloud
    running: bool
    n_particles: int  # the config's N for the next step
    # The settled estimate's modes per object (a few poses and numbers each), where the run's answer was computed
    # for this iteration's estimate (the run finished, the best estimate was taken as label, a session was
    # restored); else None: it is not drawn.
    posterior: Posterior | None = None


@dataclass
class Chosen:
    """One particle explained: its scene before and after physics and its per-pixel fit on the problem grid."""

    iteration: int
    rank: int
    index: int
    loglik: float
    weight: float
    status: int
    move: str  # the move kind that proposed it (inference.search.moves.registry.MoveKind label)
    before: np.ndarray  # (K, 4, 4) as proposed
    after: np.ndarray  # (K, 4, 4) as projected by physics (what was rendered and weighed)
    pixel_loglik: np.ndarray  # (h, w) float32, 0 where the observation has no reading
    residual: np.ndarray  # (h, w) float32 observed - predicted (m), NaN where either is missing


@dataclass
class Loaded:
    source: Source
    view: ObservationView
    # Another frame of the same sequence: the same table frame, so the 3D view keeps the user's camera.
    keep_camera: bool = False


@dataclass
class RunState:
    """Sent whenever running starts or stops, and after a reset (iteration -1: no particles yet)."""

    running: bool
    iteration: int
    reason: str = ""


@dataclass
class Stage:
    """Sent while the run works, whenever it enters another stage (``inference.clock.ORDER``): ``name``, and the
    run's ``seconds`` so far, so that a long stage (settling the answer, the posterior) is not a silent wait."""

    name: str
    seconds: float


@dataclass
class Failure:
    """Something the user must hear about. ``path``/``problem`` mirror ``InputError``."""

    title: str
    problem: str
    path: str | None = None
    fatal: bool = False  # the estimator is gone for good: only a server restart helps
    topic: str = ""  # "labels", "session" or "sequence": also shown in that tab, next to the button that failed


@dataclass
class Workers:
    """A worker pool was started: ``pids`` of its processes (empty for in-process evaluation); ``restarted`` with
    the ``reason`` when it replaced a crashed one."""

    pids: list[int]
    restarted: bool = False
    reason: str = ""


@dataclass
class Ready:
    """The engine process started."""

    pid: int


@dataclass
class Labels:
    """The engine's labels changed (frame or session loaded, snap, fit, best estimate): the panel shows these.
    ``note``: markdown saying what happened (e.g. how far the snap moved each object)."""

    labels: list  # per object (4, 4) or None
    reason: str
    note: str = ""


@dataclass
class LabelHeatmap:
    """The labelled scene's fit per pixel of the problem grid (unlabelled objects filled in, see ``filled``)."""

    pixel_loglik: np.ndarray  # (h, w) float32
    residual: np.ndarray  # (h, w) float32 observed - predicted (m), NaN where either is missing
    loglik: float
    filled: str  # how unlabelled objects were filled in: "", "best estimate" or "left out"


@dataclass
class LabelErrors:
    """The most likely scene against the labels, per object (``labels.label_errors`` rows; None where unlabelled)."""

    iteration: int
    errors: list[dict]


@dataclass
class TruthErrors:
    """The estimate against the dataset's ground truth (scene_gt.json), scored as ``workbench score`` scores a
    results CSV: per ground-truth object a row {"index", "obj_id", "position_cm", "rotation_deg", "add_s_mm",
    "right", "confidence"} (``truth.truth_rows``; NaN errors where no estimate is matched, NaN confidence before
    the run has a posterior). ``estimate``: the scored scene (K, 4, 4) in the table frame: the settled answer once
    there is one, else the best scene."""

    iteration: int
    rows: list[dict]
    estimate: np.ndarray


@dataclass
class Saved:
    """A file was written: ``kind`` "labels", "session" or "ground truth" (a backup of scene_gt.json restored)."""

    kind: str
    path: str
    note: str = ""


@dataclass
class Backups:
    """The backups of the loaded frame's scene_gt.json (``path``), newest first: per backup (its file name, when it
    was made as "YYYY-MM-DD HH:MM:SS")."""

    path: str
    backups: list[tuple[str, str]]


@dataclass
class TruthReloaded:
    """The frame's ground truth was read again, a label save or a restore having written its scene_gt.json:
    ``gt_T_world_obj`` as ``ObservationView``'s (K, 4, 4), NaN rows where unknown; None: the frame has none now.
    The truth table's rows against it follow (``TruthErrors``)."""

    gt_T_world_obj: np.ndarray | None


@dataclass
class SessionQuestion:
    """The session at ``path`` reads well but its dataset changed: load it only after the user confirms."""

    path: Path
    warnings: list[str]


@dataclass
class SessionRestored:
    """A session was loaded (``Loaded``, ``Labels`` and the last ``Snapshot`` follow or precede it): the settings
    and history to show. ``warnings``: what the user confirmed past."""

    name: str
    path: Path
    config: EstimatorConfig
    likelihood: str
    reports: list[dict]
    warnings: list[str]


@dataclass(frozen=True)
class SequenceFrame:
    """One processed frame of a sequence, for the timeline and the plots across frames. ``status``: how its run
    began ("estimated" from scratch, "tracked", "2 objects re-found", "re-initialised"); ``seconds``: the wall
    time it took (a tracked frame's Next; the first frame's iterations); ``motion``: where the camera's motion came
    from ("given", "depth"; "" when estimated from scratch); ``positions`` (K, 3) m: its answer's object positions
    in the sequence's table frame (NaN before its run has iterated); ``confidences`` (K,): each object's top
    mode's probability (NaN without a posterior); ``held``: its run can be shown again (a restored session holds
    the run of the frame it was saved on only)."""

    im_id: int
    status: str
    seconds: float
    motion: str
    positions: np.ndarray
    confidences: np.ndarray
    held: bool = True


@dataclass
class SequenceState:
    """The sequence of the loaded frame's scene, sent whenever it changes. ``scene_id`` None: the scene has one
    frame, no sequence. ``frame_ids``: the scene's image ids; ``frames``: the processed ones, in order;
    ``current``: the image id on show; ``next_id``: the frame Next goes to (None on the scene's last).
    ``reports``: where the frame on show changed, its run's history (``IterationReport.as_dict()`` each), run with
    ``run_config`` (None: the panel's settings; a tracked frame's short search has its own)."""

    scene_id: int | None
    frame_ids: tuple[int, ...] = ()
    frames: list[SequenceFrame] = field(default_factory=list)
    current: int = -1
    next_id: int | None = None
    reports: list[dict] | None = None
    run_config: EstimatorConfig | None = None


@dataclass(frozen=True)
class LabelledFrame:
    """One frame of the sequence's labels: ``im_id``; ``worst``: its worst checked object's agreement (None when
    none could be checked); ``flagged``; ``checks``: per object ``ObjectCheck.to_dict()`` with its ``reason``;
    ``checked``: a person looked at it (it was shown, or a label propagated from it)."""

    im_id: int
    worst: float | None
    flagged: bool
    checks: list[dict]
    checked: bool = False


@dataclass
class SequenceLabelState:
    """The sequence's labels and their checks, sent whenever they change (``scene_id`` None: none started).
    ``frames``: the labelled frames in order; ``gone``: (object index, obj_id, frame) per object seen through on
    every frame from that frame to the last (taken out: its label may end on the frame before); ``note``: what the
    last action did (markdown); ``fitted_frames``: the frames the last fit summed."""

    scene_id: int | None
    frames: list[LabelledFrame] = field(default_factory=list)
    gone: list[tuple[int, int, int]] = field(default_factory=list)
    note: str = ""


@dataclass
class SequenceLabelProgress:
    """The engine is at work on the sequence's labels (a long check or fit): ``text`` says what it does."""

    text: str


@dataclass
class SequenceLabelsDone:
    """The engine has done with a command of the sequence's labels, whatever came of it (the folder's buttons, which
    wait while one is out, are back)."""


Message = (Loaded | Snapshot | Chosen | RunState | Failure | Workers | Ready | Labels | LabelHeatmap | LabelErrors
           | TruthErrors | Saved | Backups | TruthReloaded | SessionQuestion | SessionRestored | SequenceState
           | SequenceLabelState | SequenceLabelProgress | SequenceLabelsDone)
