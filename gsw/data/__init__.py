"""Dataset loaders (NeRF-synthetic, instant-ngp, INRIA model folders, COLMAP, LLFF, nerfstudio), image IO and lens
undistortion.

Example:
    >>> from gsw.data import load_nerf_synthetic
    >>> train = load_nerf_synthetic("../shared/data/lego", "train", downscale=4)  # doctest: +SKIP
    >>> train.images.shape  # doctest: +SKIP
    torch.Size([87, 3, 200, 200])
"""

from __future__ import annotations

from gsw.data.colmap import camera_to_colmap, colmap_cameras, load_colmap
from gsw.data.colmap_io import ColmapError, ColmapModel, read_colmap_model, write_colmap_model
from gsw.data.distortion import (
    Distortion,
    distort_normalized,
    distort_pixels,
    undistort_image,
    undistort_normalized,
    undistort_pixels,
)
from gsw.data.images import ImageError, read_image, resize_image, write_image
from gsw.data.llff import load_llff
from gsw.data.loaders import (
    MIN_IMAGE_SIZE,
    Dataset,
    DatasetError,
    InriaModel,
    detect_format,
    holdout_indices,
    load_dataset,
    load_inria_model,
    load_instant_ngp,
    load_nerf_synthetic,
    save_inria_model,
    scene_extent,
)
from gsw.data.nerfstudio import load_nerfstudio, normalise_cameras, read_dataparser_transforms

__all__ = [
    "Dataset", "DatasetError", "Distortion", "ImageError", "InriaModel", "MIN_IMAGE_SIZE",
    "detect_format", "distort_normalized", "distort_pixels", "holdout_indices", "load_dataset",
    "load_inria_model", "load_instant_ngp", "load_nerf_synthetic", "read_image", "resize_image",
    "save_inria_model", "scene_extent", "undistort_image", "undistort_normalized",
    "undistort_pixels", "write_image",
    "ColmapError", "ColmapModel", "camera_to_colmap", "colmap_cameras", "load_colmap", "load_llff",
    "load_nerfstudio", "normalise_cameras", "read_colmap_model", "read_dataparser_transforms", "write_colmap_model",
]
