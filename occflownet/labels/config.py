"""The settings of the label pipeline (``occflownet labels``), one typed dataclass; ``docs/data.md`` explains
each rule beside Occ3D's published definition."""
from __future__ import annotations

from dataclasses import asdict, dataclass

from occflownet.occ3d import GRID, Grid
from occflownet.options import check_fields, option

UNLABELLED = 255        # point class of a sweep point that no rule could label
IGNORED_RAW = (0, 31)   # raw lidarseg noise and vehicle.ego: not surfaces of the scene, dropped
RULES = "labelling rules"  # the --help section of the rules' thresholds (docs/data.md)


@dataclass(frozen=True)
class LabelConfig:
    """How a keyframe's labels are built from a scene's LiDAR. Lengths in metres, times in seconds. `occflownet
    labels` derives its options from these fields (``occflownet/options.py``; ``ego_box`` and ``grid`` are not
    options)."""

    window: int | None = option(None, "accumulate the sweeps of this many keyframes on each side of the current "
                                      "one, and the sweeps between them (default: the whole scene, as Occ3D)", minimum=0)
    geometry_only: bool = option(False, "occupancy and masks without classes (a root without nuScenes-lidarseg): "
                                        "class 0 for every occupied voxel")
    box_margin: float = option(0.2, "a point belongs to a box grown by this much on every side", minimum=0.0,
                               group=RULES)
    box_floor: float = option(0.1, "a point without a class (a sweep point) must also lie this high above the "
                                   "box's bottom face to move with the box: lower, it is taken for the ground under "
                                   "or beside the object", minimum=0.0, group=RULES)
    track_gap: float = option(0.6, "a sweep before an instance's first or after its last annotation takes that "
                                   "annotation's box when it is at most this far away in time (keyframes are 0.5 s "
                                   "apart); farther, the instance has no box then", minimum=0.0, group=RULES)
    sweep_label_radius: float = option(0.3, "a static sweep point without lidarseg takes the class of the nearest "
                                            "labelled keyframe point within this distance (global frame, whole "
                                            "scene)", minimum=0.0, group=RULES)
    ego_box: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = \
        ((-1.2, 4.0), (-1.1, 1.1), (-0.5, 2.1))
    """Ego-frame (x, y, z) ranges of the recording vehicle: returns inside are its own body and are dropped."""
    min_points: int = option(1, "points a voxel needs to be observed occupied", minimum=1, group=RULES)
    grid: Grid = GRID

    def __post_init__(self):
        check_fields(self)

    def to_dict(self) -> dict:
        """JSON-able settings (written beside the labels, compared on a rerun)."""
        out = asdict(self)
        out["grid"] = self.grid.to_dict()
        out["ego_box"] = [list(r) for r in self.ego_box]
        return out
