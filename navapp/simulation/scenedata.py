"""Everything the viewer shows about a simulated scene, simulated once and cached.

The simulator writes a case folder (``simulation/simulate.py``); the viewer reads it back
into ``SceneData``: preoperative model, stylus data in sweep order, the iUS planes with
their poses and B-mode images, and the true deformed anatomy. A scene is simulated into
``<cache>/scenes/<key>`` where the key hashes every scene parameter, so the next start
is instant and a changed scene is simulated afresh. No viser here (the viewer and the replay
server both read scenes through it).
"""

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from ..anatomy.caseio import Case, read_case
from ..anatomy.model import VESSELS
from ..cache import cache_dir, content_key
from ..defaults import EDGE_MM
from ..features import SOURCED, STYLUS
from ..simulation.effects import Ledger
from .probe import Probe
from .scene import Scene
from .simulate import simulate
from .sources import Sight, registered
from .sources.ius import auto_segmentation as _auto_segmentation
from .sources.ius import read_frames
from .ultrasound import PlaneData

# bump when the simulator's output changes (2: the truth as a field, no registration mesh)
SCENE_CACHE_VERSION = "2"
SESSION_SCENE_VERSION = "1"  # a session's scene identity: sessions saved before stay valid


@dataclass
class SceneData:
    scene: Scene
    edge: float  # registration mesh edge, mm (the viewer's model; the simulation is apart from it)
    case_dir: Path
    case: Case  # preop, all intraop data (stylus + every plane), the truth field
    stylus: dict  # feature → (N, 3) mm, the stylus's share of case.intraop
    stylus_path: np.ndarray  # (N, 3) all stylus points in the order the tip visits them
    stylus_labels: np.ndarray  # (N,) the feature each point of stylus_path belongs to
    planes: list  # [PlaneData] of the scene's plane presets
    probe: Probe
    truth: dict  # "liver" / "portal" / "hepatic" → deformed trimesh (tracker space)
    sourced: dict = field(default_factory=dict)  # feature → (N, 3) mm of the scene's sources (``sources``)


def _scene_params(scene: Scene) -> dict:
    d = dataclasses.asdict(scene)
    d.pop("source", None)
    # a source in every scene (the stylus) keys by its settings' own names, as when they were
    # the scene's fields; a scene enabling no other source keeps the key it had before sources were rooms
    for name in [n for n in d["sources"] if registered()[n].always]:
        d.update(d["sources"].pop(name))
    if not d["sources"]:
        d.pop("sources")
    return d


def scene_key(scene: Scene, edge: float = EDGE_MM) -> str:
    """A session's identity: hash of every scene parameter and the registration mesh size
    its runs were made on. A scene built on a case folder is keyed by its path."""
    return content_key(SESSION_SCENE_VERSION, _scene_params(scene), float(edge))[:16]


def case_key(scene: Scene) -> str:
    """The simulated case folder's key: every scene parameter and the simulator's version
    (no registration mesh size: the truth is a field, apart from it)."""
    return content_key(SCENE_CACHE_VERSION, _scene_params(scene))[:16]


def _case_dir(scene: Scene, cache_root=None) -> Path:
    return (Path(cache_root) if cache_root else cache_dir()) / "scenes" / f"{scene.name}-{case_key(scene)}"


def is_simulated(scene: Scene, cache_root=None) -> bool:
    """True when ``scene``'s simulation is in the cache (``simulated_case_dir`` only reads it)."""
    return (_case_dir(scene, cache_root) / "truth" / "report.json").exists()


def simulated_case_dir(scene: Scene, cache_root=None) -> Path:
    """Simulate ``scene`` into the cache unless already there; returns the case folder."""
    out = _case_dir(scene, cache_root)
    if is_simulated(scene, cache_root):
        return out
    # written aside and swapped in whole (``outputs.staged``), under the folder's lock: a
    # half-written simulation is never mistaken for a finished one
    simulate(scene, out, cache_root=cache_root)
    return out


def sweep_order(points: np.ndarray) -> np.ndarray:
    """Order (N,) visiting the points as a stylus tip would: greedy nearest neighbour from
    the leftmost point (the simulator stores points per feature, not in one sweep)."""
    n = len(points)
    if n == 0:
        return np.zeros(0, int)
    left = np.ones(n, bool)
    order = [int(np.argmin(points[:, 0]))]
    left[order[0]] = False
    for _ in range(n - 1):
        cand = np.flatnonzero(left)
        j = cand[np.argmin(np.linalg.norm(points[cand] - points[order[-1]], axis=1))]
        order.append(int(j))
        left[j] = False
    return np.array(order)


def load_scene_data(scene: Scene, cache_root=None, edge: float = EDGE_MM) -> SceneData:
    """The scene simulated (or read from the cache) for a viewer whose registration mesh
    has edge ``edge`` mm."""
    case_dir = simulated_case_dir(scene, cache_root)
    case = read_case(case_dir)
    stylus = {k: case.intraop[k] for k in STYLUS if k in case.intraop}
    allpts = np.vstack(list(stylus.values())) if stylus else np.zeros((0, 3))
    labels = np.concatenate([[k] * len(v) for k, v in stylus.items()]) if stylus else np.zeros(0, str)
    order = sweep_order(allpts)
    planes, probe = read_frames(case_dir)
    truth = {}
    for name in ("liver", *VESSELS):
        p = case_dir / "truth" / f"{name}.ply"
        if p.exists():
            truth[name] = trimesh.load(p, process=False)
    sourced = {k: case.intraop[k] for k in SOURCED if k in case.intraop}
    return SceneData(scene, edge, case_dir, case, stylus, allpts[order], labels[order], planes, probe, truth, sourced)


def _sight(sd: SceneData) -> Sight:
    """What a frame chosen after the simulation sees: the scene's true deformed anatomy."""
    vessels = {k: sd.truth[k] for k in VESSELS if k in sd.truth}
    return Sight(sd.truth["liver"], sd.case.preop, Ledger(), vessels, tuple(sd.scene.effects), sd.scene.seed)


def _frame(sd: SceneData, index: int, probe_to_tracker: np.ndarray, live: bool) -> PlaneData:
    """One frame of the scene's tracked imaging source (the source whose ``frame`` is set:
    the iUS probe) at a pose chosen after the simulation."""
    name, source = next((n, s) for n, s in registered().items() if s.frame is not None)
    assert source.frame is not None
    return source.frame(sd.scene.sources.get(name), _sight(sd), index, np.asarray(probe_to_tracker, float), live)


def acquire_free_plane(sd: SceneData, index: int, probe_to_tracker: np.ndarray) -> PlaneData:
    """Simulate a plane at a pose the user chose (same anatomy and effects as the presets;
    the random stream is seeded by scene seed and plane index, so it is reproducible;
    ``sources/ius.frame``)."""
    return _frame(sd, index, probe_to_tracker, live=False)


def auto_segmentation(scene: Scene) -> float | None:
    """The contour error (px) of the scene's declared automatic segmentation of live
    frames, or None when the scene declares none (then live frames carry no features
    until the user draws on a frozen one)."""
    return _auto_segmentation(scene.effects)


def segment_frame(sd: SceneData, index: int, probe_to_tracker: np.ndarray) -> dict:
    """Features {name: (N, 3) mm} an automatic segmentation designates on a live frame at
    ``probe_to_tracker``: the true anatomy cut by the frame's plane (the simulated
    segmentation), its contours perturbed by the declared ``auto_segmentation`` error in
    place of any ``contour_jitter``, and the scene's other effects as for any plane. Empty
    when the scene declares no automatic segmentation (``sources/ius.frame``)."""
    return _frame(sd, index, probe_to_tracker, live=True).features
