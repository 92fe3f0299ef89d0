"""reconstruct, the pair cache, build_pairs, export_adapter and in-process FM-DPO training."""

from __future__ import annotations

import json
import os
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

from . import _core
from ._core import PairCacheReader, PairCacheWriter, Scene
from ._stage1 import ArrayLike, Masks, Stage1

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["reconstruct", "build_pairs", "export_adapter", "train_fmdpo", "PairCacheReader", "PairCacheWriter",
           "validate_pair_cache"]


def reconstruct(image: ArrayLike, masks: Masks, *, out: PathLike, pointmap: Optional[ArrayLike] = None,
                depth: Optional[ArrayLike] = None, K: Optional[Union[ArrayLike, Mapping[str, float]]] = None,
                objects: Optional[Union[PathLike, Sequence[Mapping[str, Any]]]] = None, stage1: Optional[Stage1] = None,
                overwrite: bool = False, probe_config: Optional[PathLike] = None,
                overrides: Optional[Mapping[str, Any]] = None, run_probe: bool = True, seed: int = 0,
                lift_samples: int = 4) -> Dict[str, Any]:
    """The ``reconstruct`` program's steps on arrays, with models loaded once (pass the same Stage1 each call).

    objects: the sidecar (a JSON file, or its entries as dicts: id / label_value, label, role, dof, pins,
    base, fit ("lift" or "box": a base fitted as a box to its depth), mesh + pose, refined_pose;
    docs/reconstruct.md). Writes into ``out`` what the program writes
    (input/scene.json, reconstruct_report.json, probe/...). Returns {"scene": Scene (pre-simulation),
    "objects": per-object reports, "messages", "timings", "up", "probe_report", "out_dir"}. lift_samples:
    shapes drawn per lifted object, each aligned and the one the depth and mask agree with most kept (0:
    the Stage1's num_samples; docs/reconstruct.md).
    """
    return _core.reconstruct(image, masks, pointmap=pointmap, depth=depth, K=K, objects=objects,
                             stage1=None if stage1 is None else stage1._core, out=out, overwrite=overwrite,
                             probe_config=probe_config, overrides=None if overrides is None else dict(overrides),
                             run_probe=run_probe, seed=seed, lift_samples=lift_samples)


def validate_pair_cache(path: PathLike) -> Dict[str, Any]:
    """Full scan of a pair cache (every record decoded and checked); returns its info."""
    return _core.validate_pair_cache(path)


def build_pairs(manifest: PathLike, out: PathLike, *, stage1: Stage1, cond_mode: str = "tokens",
                dtype: str = "float16", inputs_storage: str = "exact", batch: int = 4, seed: int = 0,
                resume: bool = True, commit_every: int = 256, preprocess: str = "released") -> Dict[str, Any]:
    """The ``build_pairs`` program with a loaded Stage1: a JSON-lines manifest of image pairs -> pair cache.

    Bad records are skipped and listed in the report's "issues". Ctrl-C commits what is done and raises
    KeyboardInterrupt (run again to continue: an existing cache is resumed).
    """
    return _core.build_pairs(manifest, out, stage1=stage1._core, cond_mode=cond_mode, dtype=dtype,
                             inputs_storage=inputs_storage, batch=batch, seed=seed, resume=resume,
                             commit_every=commit_every, preprocess=preprocess)


def export_adapter(source: PathLike, out: PathLike, *, merge: bool = False, overwrite: bool = False,
                   model_config: Optional[PathLike] = None, weights: Optional[PathLike] = None,
                   run_config: Optional[PathLike] = None, sets: Sequence[str] = (), description: str = "") -> None:
    """The ``export_adapter`` program: a checkpoint's (or PEFT dir's) adapter -> a PEFT directory, or with
    merge=True the base generator with the adapter merged in (one safetensors file)."""
    _core.export_adapter(source, out, merge=merge, overwrite=overwrite, model_config=model_config, weights=weights,
                         run_config=run_config, sets=list(sets), description=description)


def _override_strings(overrides: Union[Mapping[str, Any], Sequence[str], None]) -> List[str]:
    if overrides is None:
        return []
    if isinstance(overrides, Mapping):
        out: List[str] = []
        for k, v in overrides.items():
            text = ("true" if v else "false") if isinstance(v, bool) else v if isinstance(v, str) else json.dumps(v)
            out.append(f"{k}={text}")
        return out
    return [str(s) for s in overrides]


def train_fmdpo(config: PathLike, overrides: Union[Mapping[str, Any], Sequence[str], None] = None, *,
                resume: Optional[str] = None, overwrite: bool = False) -> Dict[str, Any]:
    """FM-DPO training (the ``train_fmdpo`` program) on ONE rank in this process.

    overrides: {"optim.lr": 2e-5} or ["optim.lr=2e-5"] (the program's --set). resume: "latest" or a
    checkpoint dir. Returns {"steps", "out_dir", "adapter", "metrics": the metrics.jsonl rows}. Several
    GPUs: run the program itself, ``torchrun --nproc-per-node N --no-python build/train_fmdpo --config ...``
    (or ``build/train_fmdpo --nproc-per-node N ...``), not this call.
    """
    res = _core.train_fmdpo(config, _override_strings(overrides), resume=resume or "", overwrite=overwrite)
    metrics_path = os.path.join(res["out_dir"], "metrics.jsonl")
    rows: List[Dict[str, Any]] = []
    if os.path.exists(metrics_path):
        with open(metrics_path) as f:
            rows = [json.loads(line) for line in f if line.strip()]
    res["metrics"] = rows
    return res
