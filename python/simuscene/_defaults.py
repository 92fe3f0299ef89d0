"""Where the default Stage-1 model files come from.

The defaults are the released-size configs with no weights. Given no weights at all (and not
``random_weights=True``), the native core loads the shipped miniature instead (weights/miniature_cpu in
the source tree, or $SIMU_DEFAULT_MODEL; docs/miniature.md): a small Stage-1 model trained on the
procedural shape world, not SAM 3D. Weight paths select the released model.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, Optional

from . import _core


def _configs_dir() -> Path:
    """The package's configs (wheel install) or the source tree's (build tree)."""
    packaged = Path(__file__).resolve().parent / "configs"
    return packaged if packaged.is_dir() else Path(_core.source_dir) / "configs"


def stage1_files() -> Dict[str, Optional[str]]:
    """Default config and weight files of Stage1 (keys as Stage1's parameters; None = not given)."""
    c = _configs_dir()
    return {
        "generator_config": os.fspath(c / "stage1_real.yaml"),
        "generator_weights": None,
        "decoder_config": os.fspath(c / "ss_decoder.yaml"),
        "decoder_weights": None,
        "embedder_config": os.fspath(c / "cond_embedder_sam3d_stage1.yaml"),
        "embedder_weights": None,
    }
