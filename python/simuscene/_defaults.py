"""Where the default Stage-1 model files come from: the one place to change when the miniature model ships.

Today the defaults are the released-size configs with no weights (``Stage1()`` then needs
``random_weights=True`` or weight paths). When the miniature default model is shipped, this function
returns its configs and weights and every caller picks them up.
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
