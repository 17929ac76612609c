"""The capture script: which sequences exist, their timelines, light patterns and motions.

Following the paper's table "Data Capture" (plus the in-the-wild demo):

=============== ======= ===== ====================== ==========================================
sequence        studio  HMD   ego streams            light pattern (after the sync prefix)
=============== ======= ===== ====================== ==========================================
handeye         yes     on    down + front           flat; a ChArUco board stands in front
ego_train       yes     on    down + front           flat
ego_bulk        track   on    down                   flat (the headset views at the scale learning needs)
relight_train   yes     off   none                   flat / HDR envmap alternating (train maps)
test            yes     on    down + front           unseen HDR envmaps (test maps, ``--envmap``)
wild            no      on    down + front, tracker  none (an unseen environment lights the body)
=============== ======= ===== ====================== ==========================================

**Timeline and sync.** Studio frame ids are 0..N-1 at the sequence fps. Sequences with both
studio and ego streams start with ``lead`` frames of dim *standby* light (pattern ``flat`` with a
small ``scale``), then a known code of ``flash`` (bright flat) and ``dark`` frames
(``sync.code``), then the content. The ego stream starts ``ego_offset`` frames after the studio
(1..``sync.max_offset``, seeded, ground truth only) and numbers its frames from 0: ego frame ``e``
was exposed together with studio frame ``e + ego_offset``. Per-frame brightness of the two
streams cross-correlated over the flash code recovers the offset. The ego cameras run at the
studio fps here (30 fps in the paper); ``relight_train`` (60 fps in the paper) has no ego stream.

**Headset-only sequences** (``ego_bulk``, purpose ``ego_train``): long sessions for the egocentric
networks (egopose needs >= 1,000 frames; issue 21) in which only the head-tracking studio cameras
record (for the head poses) and the headset only its down-facing cameras. A frame costs about
half of an ``ego_train`` frame (1.15 s against about 2.5 s at the cpu preset): no studio views,
masks, normals or reconstructions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.structures.character import Character
from egorelight_cli.synth.motions import SCRIPTED, Segment, compose_motion

SEQUENCES = ("handeye", "ego_train", "relight_train", "test", "wild", "ego_bulk")
#: name -> (has studio, HMD worn)
LAYOUT = {"handeye": (True, True), "ego_train": (True, True), "relight_train": (True, False),
          "test": (True, True), "wild": (False, True), "ego_bulk": (True, True)}
#: name -> purpose (``sequence.json``), where they differ
PURPOSES = {"ego_bulk": "ego_train"}
#: sequences whose studio records only the head-tracking cameras and whose headset records only
#: its down-facing cameras
HEADSET_ONLY = frozenset({"ego_bulk"})
_SEED_CODES = {name: i + 1 for i, name in enumerate(SEQUENCES)}


@dataclass
class SequencePlan:
    """Everything needed to simulate one sequence.

    Attributes:
        name: sequence name (its purpose: :data:`PURPOSES`, else the name).
        fps: frame rate of the studio (and ego) stream.
        frame_ids: (N,) frame ids of the simulated timeline (studio ids; for ``wild``, ego ids).
        lights: per frame ``{"pattern", "envmap", "yaw_deg", "olat_index", "scale"}`` (studio light).
        theta: (N,D) the motion at every timeline frame.
        has_studio: whether studio cameras record.
        hmd_on: whether the subject wears the HMD.
        ego_offset: ego frame e <-> timeline frame e + ego_offset (None without an ego stream).
        segments: the motion script (for the record).
        held_out: names of held-out studio cameras (test only).
        wild_envmap: the environment (name) of the in-the-wild sequence.
        wild_yaw_deg: its rotation.
        sync: ``{"code", "standby_frames", "code_start_frame"}`` of the flash prefix ({} without one).
        tracker_theta: wild only: (N*k,D) the motion sampled ``k = tracker_theta.shape[0] // N``
            times per frame (sample ``j`` at ``j / (k fps)`` s), for the headset tracker's higher rate.
        headset_only: only the head-tracking studio cameras and the down-facing ego cameras record.
    """

    name: str
    fps: float
    frame_ids: np.ndarray
    lights: list[dict]
    theta: np.ndarray
    has_studio: bool
    hmd_on: bool
    ego_offset: int | None
    segments: list[Segment]
    held_out: list[str] = field(default_factory=list)
    wild_envmap: str | None = None
    wild_yaw_deg: float = 0.0
    sync: dict = field(default_factory=dict)
    tracker_theta: np.ndarray | None = None
    headset_only: bool = False

    @property
    def purpose(self) -> str:
        return PURPOSES.get(self.name, self.name)

    @property
    def num_frames(self) -> int:
        return len(self.frame_ids)

    @property
    def has_ego(self) -> bool:
        return self.ego_offset is not None

    def ego_frame_ids(self) -> np.ndarray:
        """(N,) ego frame id of every timeline frame, -1 where the ego stream was not recording."""
        if self.ego_offset is None:
            return np.full(self.num_frames, -1, dtype=np.int64)
        ids = self.frame_ids - self.ego_offset
        return np.where(ids >= 0, ids, -1)

    def content_mask(self) -> np.ndarray:
        """(N,) bool: frames after the standby/sync prefix."""
        return np.array([light.get("content", True) for light in self.lights])


def light_entry(pattern: str, scale: float = 1.0, envmap: str | None = None, yaw_deg: float = 0.0,
                olat_index: int | None = None, content: bool = True) -> dict:
    return {"pattern": pattern, "envmap": envmap, "yaw_deg": float(yaw_deg), "olat_index": olat_index,
            "scale": float(scale), "content": content}


def light_tail(cfg, scfg, rng: np.random.Generator) -> list[dict]:
    """The test sequence's robustness tail: ``olat_tail`` one-light-at-a-time frames (distinct
    seeded lights, brightened by ``olat_scale``) then ``group_tail`` frames lit by a random quarter
    of the lights."""
    num_lights = int(cfg.lights.num_lights)
    olat = rng.choice(num_lights, size=min(int(scfg.olat_tail), num_lights), replace=False)
    out = [light_entry("olat", float(scfg.olat_scale), olat_index=int(i)) for i in olat]
    for _ in range(int(scfg.group_tail)):
        ids = np.sort(rng.choice(num_lights, size=max(num_lights // 4, 1), replace=False))
        out.append({**light_entry("group", cfg.lights.flat_intensity), "light_ids": ids.tolist()})
    return out


def sync_prefix(cfg, rng: np.random.Generator) -> tuple[list[dict], int]:
    """Standby + flash code light entries, and the seeded ego offset."""
    offset = int(rng.integers(1, int(cfg.sync.max_offset) + 1))
    lead = int(cfg.sync.max_offset) + 1
    lights = [light_entry("flat", cfg.lights.standby_intensity, content=False) for _ in range(lead)]
    for bit in cfg.sync.code:
        lights.append(light_entry("flash", cfg.lights.flash_intensity, content=False) if bit
                      else light_entry("dark", 0.0, content=False))
    return lights, offset


def _motion_segments(purpose: str, scfg, motion_types, rng: np.random.Generator) -> list[Segment]:
    if purpose == "handeye":
        return [Segment("handeye_looking", 1e9)]
    if purpose == "wild":
        return [Segment("turning_scan", float(scfg.scan_s)), Segment("casual", 1e9)]
    types = list(motion_types) if motion_types else list(SCRIPTED)
    if purpose == "relight_train":
        types = types[::-1]  # the same repertoire, repeated in another order
    if purpose in ("test", "ego_bulk"):  # ego_bulk: the repertoire in its own order, new instances
        order = list(rng.permutation(types))
        return [Segment(m, float(scfg.segment_s)) for m in order]
    return [Segment(m, float(scfg.segment_s)) for m in types]


def plan_sequence(name: str, cfg, character: Character | None, seed: int, train_envmaps: list[str],
                  test_envmaps: list[str], wild_envmaps: list[str], held_out: list[str],
                  motion_theta: np.ndarray | None = None) -> SequencePlan:
    """The plan of sequence ``name`` from the synth config.

    ``motion_theta`` (M,D), when given (``--motion``), replaces the motion library: frames are
    taken from it in order (looping).
    """
    if name not in LAYOUT:
        raise EgorelightError(f"unknown sequence {name!r}; known: {', '.join(SEQUENCES)}")
    scfg = cfg.sequences[name]
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _SEED_CODES[name]]))
    has_studio, hmd_on = LAYOUT[name]
    fps = float(scfg.fps)
    lights: list[dict] = []
    offset = None
    sync: dict = {}
    if has_studio and hmd_on:
        lights, offset = sync_prefix(cfg, rng)
        standby = len(lights) - len(cfg.sync.code)
        sync = {"code": [int(b) for b in cfg.sync.code], "standby_frames": standby, "code_start_frame": standby}
    content = int(scfg.frames)
    wild_envmap, wild_yaw = None, 0.0
    if name in ("handeye", "ego_train", "ego_bulk"):
        lights += [light_entry("flat", cfg.lights.flat_intensity) for _ in range(content)]
    elif name == "relight_train":
        if not train_envmaps:
            raise EgorelightError("relight_train needs at least one training environment map")
        for i in range(content):
            if i % 2 == 0:
                lights.append(light_entry("flat", cfg.lights.flat_intensity))
            else:
                lights.append(light_entry("envmap", cfg.lights.envmap_scale, envmap=str(rng.choice(train_envmaps)),
                                          yaw_deg=float(rng.uniform(0, 360))))
    elif name == "test":
        if not test_envmaps:
            raise EgorelightError("the test sequence needs at least one test environment map")
        # One map for most of the sequence, then the next ones for the final part (the paper's
        # orange ... orange blue).
        n_maps = len(test_envmaps)
        first = int(np.ceil(content * (0.75 if n_maps > 1 else 1.0)))
        yaws = rng.uniform(0, 360, size=n_maps)
        for i in range(content):
            k = 0 if i < first else 1 + (i - first) * (n_maps - 1) // max(content - first, 1)
            lights.append(light_entry("envmap", cfg.lights.envmap_scale, envmap=test_envmaps[k], yaw_deg=yaws[k]))
        lights += light_tail(cfg, scfg, rng)
    else:  # wild: no studio lights; the environment lights the subject
        if not wild_envmaps:
            raise EgorelightError("the wild sequence needs an environment map")
        wild_envmap = wild_envmaps[0]
        wild_yaw = float(rng.uniform(0, 360))
        lights = [light_entry("envmap", 1.0, envmap=wild_envmap, yaw_deg=wild_yaw) for _ in range(content)]
        offset = 0
    n = len(lights)
    frame_ids = np.arange(n, dtype=np.int64)
    if motion_theta is not None:
        theta = np.asarray(motion_theta, dtype=np.float64)[np.arange(n) % len(motion_theta)]
        segments = [Segment("from_file", n / fps)]
    else:
        segments = _motion_segments(name, scfg, cfg.motion_types, rng)
        facing = {"heading_range": 0.0, "origin_range": 0.0} if name == "handeye" else {}  # face the board
        motion_seed = int(rng.integers(1 << 31))
        theta = compose_motion(character, segments, fps, n, seed=motion_seed, **facing)
        if name == "test":
            casual = float(scfg.casual_s)
            n_casual = min(n, round(casual * fps))
            if n_casual > 0:  # the unscripted end: casual motion cross-faded in
                tail = compose_motion(character, [Segment("casual", 1e9)], fps, n, seed=int(rng.integers(1 << 31)))
                ramp = np.clip((np.arange(n) - (n - n_casual)) / max(0.4 * fps, 1.0), 0, 1)[:, None]
                ramp = ramp * ramp * (3 - 2 * ramp)
                theta = (1 - ramp) * theta + ramp * tail
                segments = segments + [Segment("casual", casual)]
    tracker_theta = None
    if name == "wild":  # the headset tracker samples the same motion k times per frame
        k = int(cfg.wild.tracker.samples_per_frame)  # >= 1 (stages/synth.yaml's checks)
        if motion_theta is None:
            tracker_theta = compose_motion(character, segments, k * fps, k * n, seed=motion_seed)
        else:  # a motion file has frames only: interpolate between them
            fine = np.arange(k * n) / k
            tracker_theta = np.stack([np.interp(fine, np.arange(n), theta[:, c]) for c in range(theta.shape[1])], 1)
    return SequencePlan(name=name, fps=fps, frame_ids=frame_ids, lights=lights, theta=theta, has_studio=has_studio,
                        hmd_on=hmd_on, ego_offset=offset, segments=segments,
                        held_out=list(held_out) if name == "test" else [],
                        wild_envmap=wild_envmap, wild_yaw_deg=wild_yaw, sync=sync, tracker_theta=tracker_theta,
                        headset_only=name in HEADSET_ONLY)
