"""The settings of the label pipeline (``occflownet labels``), one typed dataclass; ``docs/labels.md`` explains
each rule beside Occ3D's published definition."""
from __future__ import annotations

from dataclasses import asdict, dataclass

from occflownet.occ3d import GRID, Grid

UNLABELLED = 255        # point class of a sweep point that no rule could label
IGNORED_RAW = (0, 31)   # raw lidarseg noise and vehicle.ego: not surfaces of the scene, dropped


@dataclass(frozen=True)
class LabelConfig:
    """How a keyframe's labels are built from a scene's LiDAR. Lengths in metres, times in seconds."""

    window: int | None = None
    """Keyframes on each side of the current one whose sweeps (and the sweeps between them) are accumulated;
    None: the whole scene, as Occ3D."""
    geometry_only: bool = False
    """Occupancy and masks without classes (a root without lidarseg): every occupied voxel gets class 0."""
    box_margin: float = 0.2
    """A point belongs to a box grown by this much on every side."""
    box_floor: float = 0.1
    """A point without a class (a sweep point) must also lie this high above the box's bottom face: lower, it is
    taken for the ground under or beside the object (a point with a lidarseg class moves with a box only when it
    has the box's class)."""
    track_gap: float = 0.6
    """A sweep before an instance's first or after its last annotation takes that annotation's box when it is at
    most this far away in time (nuScenes keyframes are 0.5 s apart); farther, the instance has no box then."""
    sweep_label_radius: float = 0.3
    """A static sweep point without lidarseg takes the class of the nearest labelled keyframe point within this
    distance (global frame, whole scene)."""
    ego_box: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = \
        ((-1.2, 4.0), (-1.1, 1.1), (-0.5, 2.1))
    """Ego-frame (x, y, z) ranges of the recording vehicle: returns inside are its own body and are dropped."""
    min_points: int = 1
    """Points a voxel needs to be observed occupied."""
    grid: Grid = GRID

    def __post_init__(self):
        if self.window is not None and self.window < 0:
            raise ValueError(f"window must be None (whole scene) or >= 0 keyframes, got {self.window}")
        for name in ("box_margin", "box_floor", "track_gap", "sweep_label_radius"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.min_points < 1:
            raise ValueError(f"min_points must be >= 1, got {self.min_points}")

    def to_dict(self) -> dict:
        """JSON-able settings (written beside the labels, compared on a rerun)."""
        out = asdict(self)
        out["grid"] = self.grid.to_dict()
        out["ego_box"] = [list(r) for r in self.ego_box]
        return out
