"""Dataset access: sample index, loaders, rays, class weights (nuScenes-format roots, real or synthetic).

Modules (numpy only; nothing here imports torch):
- ``tables``: read the nuScenes JSON tables (``load_tables``, ``DatasetError``);
- ``builder``: tables → ``SampleIndex`` (``build_index``);
- ``index``: ``SampleIndex`` (records, splits, temporal neighbours), ``save_index`` / ``load_index``;
- ``records``: ``SampleRecord``, ``CameraRecord``, ``LidarRecord``, ``Boxes``, ``EgoBoxes``;
- ``loaders``: images, LiDAR, lidarseg, Occ3D occupancy;
- ``rays``: LiDAR → camera rays in the current ego frame (``RayBuilder``, ``RayBatch``, ``sample_rays``);
- ``class_weights``: class counts N_c and weights ω(c).
"""
from occflownet.data.index import SampleIndex, load_index, save_index
from occflownet.data.tables import DatasetError

__all__ = ["DatasetError", "SampleIndex", "load_index", "save_index"]
