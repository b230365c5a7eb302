"""Datasets with a known truth, written in the ordinary dataset format (``capture.dataset``), so that the pipeline
reads them like photos of a real object.

- :mod:`capture.synth.scenes`: meshes, camera and light rigs, procedural ground-truth maps of any registered model,
  photos through the photo model (``capture.photo``); :func:`make_synthetic`, :func:`default_scene` (the README
  demo), :func:`small_scene`;
- :mod:`capture.synth.measured`: objects whose regions are measured materials (NBRDF fits of MERL) on the same
  rigs; :func:`make_measured_scene`, the truth in ``meta.measured`` (:func:`read_truth`).
"""

from .measured import (
    DEFAULT_MATERIALS,
    MeasuredSceneConfig,
    MeasuredSceneError,
    make_measured_scene,
    measured_scene,
    read_truth,
    region_map,
    render_measured,
    render_measured_scene,
)
from .scenes import (
    BUILTIN_MESHES,
    CAMERA_RIGS,
    LIGHT_RIGS,
    REGION_NAMES,
    SAMPLING,
    Scene,
    SyntheticConfig,
    SyntheticError,
    build_cameras,
    build_lights,
    build_mesh,
    build_scene,
    default_scene,
    highlight_coverage,
    make_synthetic,
    procedural_maps,
    render_scene,
    small_scene,
)

__all__ = [
    "BUILTIN_MESHES", "CAMERA_RIGS", "DEFAULT_MATERIALS", "LIGHT_RIGS", "REGION_NAMES", "SAMPLING",
    "MeasuredSceneConfig", "MeasuredSceneError", "Scene", "SyntheticConfig", "SyntheticError", "build_cameras",
    "build_lights", "build_mesh", "build_scene", "default_scene", "highlight_coverage", "make_measured_scene",
    "make_synthetic", "measured_scene", "procedural_maps", "read_truth", "region_map", "render_measured",
    "render_measured_scene", "render_scene", "small_scene",
]
