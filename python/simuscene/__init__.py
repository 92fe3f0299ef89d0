"""simuscene: the SimuScene resampler toolkit (C++/LibTorch) inside a Python pipeline, in-process.

    import simuscene as ss
    stage1 = ss.Stage1(generator_weights=..., decoder_weights=..., embedder_weights=...)
    lifted = stage1.lift(rgb_uint8, {"cup": mask}, pointmap=moge_points)
    result = ss.probe(lifted.to_scene(), config="configs/probe.yaml", resampler=stage1, out="out/probe")

Tensors cross as the same torch storage (torch's own pybind11 casters); numpy inputs are shared through
torch.from_numpy. Long calls release the GIL and stop on Ctrl-C; log lines go to logging.getLogger("simuscene").
Docs: docs/python.md.
"""

from __future__ import annotations

import atexit
import logging

import torch  # noqa: F401  (loads libtorch before the extension module)

from . import _core, errors
from ._core import (BaseBody, Camera, PairCacheReader, PairCacheWriter, Plane, Scene, SceneObject, read_depth,
                    read_image, read_intrinsics, read_mask, read_mesh, read_pointmap, set_log_level, write_image)
from ._pipeline import build_pairs, export_adapter, reconstruct, train_fmdpo, validate_pair_cache
from ._probe import Candidate, ProbeDecision, ProbeResult, probe
from ._stage1 import LiftedObject, LiftResult, Shape, Stage1
from .errors import ConfigError, Error, InputError, MissingFileError

__all__ = [
    "Stage1", "LiftResult", "LiftedObject", "Shape",
    "Scene", "SceneObject", "Camera", "Plane", "BaseBody",
    "probe", "ProbeResult", "ProbeDecision", "Candidate",
    "reconstruct", "build_pairs", "export_adapter", "train_fmdpo",
    "PairCacheReader", "PairCacheWriter", "validate_pair_cache",
    "read_image", "read_mask", "read_depth", "read_pointmap", "read_intrinsics", "read_mesh", "write_image",
    "set_log_level", "errors", "Error", "ConfigError", "InputError", "MissingFileError",
]

logging.getLogger("simuscene").addHandler(logging.NullHandler())
atexit.register(_core._shutdown)
