"""Box tracks: interpolation between keyframe annotations, the time gap rule, and which box a point lies in."""
import numpy as np

from occflownet.geometry import quaternion_to_matrix, slerp, yaw_to_quaternion
from occflownet.labels.tracks import BoxTracks, points_in_boxes


def track(times, centres, yaws, size=(2.0, 4.0, 1.5)):
    return BoxTracks(tokens=("a",), labels=np.array([4], np.uint8), times=(np.array(times, np.int64),),
                     centers=(np.array(centres, float),),
                     rotations=(np.array([yaw_to_quaternion(y) for y in yaws]),),
                     sizes=(np.array([size] * len(times), float),))


def test_boxes_between_and_around_annotations():
    tracks = track([0, 1_000_000], [[0, 0, 1], [10, 4, 1]], [0.0, 0.6])
    mid = tracks.at(250_000)
    assert list(mid.instance) == [0]
    assert np.allclose(mid.box2global[0][:3, 3], [2.5, 1.0, 1.0])
    yaw = np.arctan2(mid.box2global[0][1, 0], mid.box2global[0][0, 0])
    assert np.isclose(yaw, 0.15)                                   # slerp of a yaw is linear in the angle
    assert np.allclose(mid.half[0], [2.0, 1.0, 0.75])              # (l, w, h) / 2 from (w, l, h)
    assert np.allclose(tracks.at(1_000_000).box2global[0][:3, 3], [10, 4, 1])
    assert len(tracks.at(-300_000)) == 0                           # before the first annotation, no gap allowed
    assert np.allclose(tracks.at(-300_000, gap_s=0.5).box2global[0][:3, 3], [0, 0, 1])
    assert len(tracks.at(1_700_000, gap_s=0.5)) == 0               # 0.7 s after the last one


def test_slerp_takes_the_short_way():
    q0, q1 = yaw_to_quaternion(3.0), -yaw_to_quaternion(-3.0)      # ±3 rad: 0.28 rad apart through ±π
    R = quaternion_to_matrix(slerp(q0, q1, 0.5))
    assert np.isclose(abs(np.arctan2(R[1, 0], R[0, 0])), np.pi)


def test_points_in_boxes_margin_and_nearest_centre():
    tracks = BoxTracks(tokens=("a", "b"), labels=np.array([4, 10], np.uint8),
                       times=(np.array([0]), np.array([0])),
                       centers=(np.array([[0.0, 0.0, 0.75]]), np.array([[4.3, 0.0, 0.75]])),
                       rotations=(np.array([yaw_to_quaternion(0.0)]), np.array([yaw_to_quaternion(np.pi / 2)])),
                       sizes=(np.array([[2.0, 4.0, 1.5]]), np.array([[2.0, 4.0, 1.5]])))
    boxes = tracks.at(0)
    pts = np.array([[1.9, 0.0, 0.75],      # inside a (x half-length 2)
                    [2.15, 0.9, 0.75],     # 0.15 beyond a's end, inside the 0.2 margin; b (rotated) ends at 3.3
                    [3.25, 0.0, 0.75],     # in b only (b's half width 1 along x: 3.3 .. 5.3, with margin 3.1)
                    [2.8, 0.0, 1.6],       # between: 0.8 beyond a, 0.3 before b's margin: none
                    [0.0, 0.0, 1.6]])      # 0.1 above a's top: inside with the margin
    which, local = points_in_boxes(pts, boxes, margin=0.2)
    assert which.tolist() == [0, 0, 1, -1, 0]
    assert np.allclose(local[2], [0.0, 1.05, 0.0])                 # b's x axis points along +y
    which, _ = points_in_boxes(np.array([[2.0, 0.0, 0.75]]), boxes, margin=1.4)   # in both: nearest centre (a)
    assert which.tolist() == [0]
