"""Stage1 (SAM 3D Objects Stage 1, loaded once) and the results of its lift."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Union

import numpy as np
import torch

from . import _core
from ._defaults import stage1_files
from ._core import LiftedObject, Scene, Shape

PathLike = Union[str, "os.PathLike[str]"]
ArrayLike = Union[np.ndarray, torch.Tensor]
Masks = Union[ArrayLike, Mapping[str, ArrayLike], Sequence[ArrayLike]]

__all__ = ["Stage1", "LiftResult", "LiftedObject", "Shape"]

_temp_dirs: List[str] = []


@atexit.register
def _remove_temp_dirs() -> None:
    for d in _temp_dirs:
        shutil.rmtree(d, ignore_errors=True)


class LiftResult:
    """What Stage1.lift returns: one LiftedObject per input object, in input order.

    ``result["cup"]`` finds an object by id. ``write(out)`` writes exactly what the ``lift`` program
    writes; ``to_scene()`` makes the probe's Scene from it (the program's scene.json, read back).
    """

    def __init__(self, run: _core.LiftRun) -> None:
        self._run = run
        self.objects: List[LiftedObject] = list(run.objects)

    def __len__(self) -> int:
        return len(self.objects)

    def __iter__(self) -> Iterator[LiftedObject]:
        return iter(self.objects)

    def __getitem__(self, key: Union[int, str]) -> LiftedObject:
        if isinstance(key, int):
            return self.objects[key]
        for o in self.objects:
            if o.id == key:
                return o
        raise KeyError(f"no lifted object '{key}' (ids: {', '.join(o.id for o in self.objects)})")

    @property
    def failed(self) -> int:
        """Number of objects that are not ok (each carries its error)."""
        return self._run.failed

    @property
    def seconds(self) -> Dict[str, float]:
        """Seconds per stage for the whole call: preprocess, embed, sample, decode, mesh, pose, total."""
        return self._run.seconds

    @property
    def pointmap(self) -> torch.Tensor:
        """The point map used [H, W, 3]: the tensor handed in (same storage) when it was float32 CPU contiguous."""
        return self._run.pointmap

    @property
    def K(self) -> Dict[str, float]:
        """The intrinsics used {fx, fy, cx, cy} (given, or fitted to the point map)."""
        return self._run.K

    def write(self, out: PathLike, *, overwrite: bool = False, image_path: Optional[PathLike] = None,
              depth_path: Optional[PathLike] = None) -> None:
        """Writes the lift program's outputs into ``out`` (scene.json, report.json, objects/<id>/...)."""
        self._run.write(out, overwrite, image_path, depth_path)

    def to_scene(self, out: Optional[PathLike] = None, *, overwrite: bool = False,
                 image_path: Optional[PathLike] = None, depth_path: Optional[PathLike] = None) -> Scene:
        """The lifted objects as a probe Scene: the lift program's files written to ``out`` (or a temp
        folder removed at exit) and its scene.json read back (camera, gravity +y, the ok objects). The
        scene's image and point map (what the probe's resampler reads) are the given files, else the
        arrays used, saved to a temp folder (uint8 image: exact for 8-bit inputs)."""
        if out is None:
            parent = tempfile.mkdtemp(prefix="simuscene-lift-")
            _temp_dirs.append(parent)
            out = os.path.join(parent, "lift")
        if image_path is None or depth_path is None:
            # The probe's resampler reads the photo from files: the arrays used, saved once.
            keep = tempfile.mkdtemp(prefix="simuscene-photo-")
            _temp_dirs.append(keep)
            if image_path is None:
                image_path = os.path.join(keep, "image.png")
                rgb = (self._run.image.permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()
                _core.write_image(image_path, rgb)
            if depth_path is None:
                depth_path = os.path.join(keep, "pointmap.npy")
                np.save(depth_path, self._run.pointmap.numpy())
        self.write(out, overwrite=overwrite, image_path=image_path, depth_path=depth_path)
        return Scene.load(os.path.join(os.fspath(out), "scene.json"))


class Stage1:
    """SAM 3D Objects Stage 1 (condition embedder, flow generator, sparse-structure decoder), loaded once.

    Files default to ``simuscene._defaults.stage1_files()``. With no weights at all, the shipped miniature
    loads (weights/miniature_cpu: trained on the procedural shape world, not SAM 3D; docs/miniature.md);
    pass the converted released checkpoints for SAM 3D, or ``random_weights=True`` for random weights.
    ``adapter`` loads a PEFT LoRA adapter directory. Every model call takes the object's lock, so one
    Stage1 serves many threads in turn; the calls release the GIL.
    """

    def __init__(self, generator_config: Optional[PathLike] = None, generator_weights: Optional[PathLike] = None,
                 decoder_config: Optional[PathLike] = None, decoder_weights: Optional[PathLike] = None,
                 embedder_config: Optional[PathLike] = None, embedder_weights: Optional[PathLike] = None, *,
                 adapter: Optional[PathLike] = None, random_weights: bool = False, device: str = "auto",
                 precision: str = "auto", steps: int = 25, num_samples: int = 1) -> None:
        files: Dict[str, Optional[str]] = stage1_files()
        given = {"generator_config": generator_config, "generator_weights": generator_weights,
                 "decoder_config": decoder_config, "decoder_weights": decoder_weights,
                 "embedder_config": embedder_config, "embedder_weights": embedder_weights}
        for key, value in given.items():
            if value is not None:
                files[key] = os.fspath(value)
        self._core = _core.Stage1Core(files, random_weights, device, precision, steps, num_samples,
                                      None if adapter is None else os.fspath(adapter))

    @property
    def device(self) -> str:
        """The device the models run on ("cpu", "cuda:0", ...)."""
        return self._core.device

    @property
    def precision(self) -> str:
        """The precision the models run in ("fp32", "fp16", "bf16")."""
        return self._core.precision

    @property
    def has_adapter(self) -> bool:
        return self._core.has_adapter

    @property
    def random_weights_banner(self) -> str:
        """The RANDOM WEIGHTS warning when some module runs on random init ("" otherwise)."""
        return self._core.random_weights_banner

    @property
    def config(self) -> Dict[str, Any]:
        """The files and sampler settings in use."""
        return self._core.config

    def load_adapter(self, path: PathLike) -> None:
        """Loads a PEFT LoRA adapter directory into the generator (replacing one loaded before)."""
        self._core.load_adapter(path)

    def enable_adapter(self) -> None:
        """Switches the loaded adapter on (the default after loading)."""
        self._core.set_adapter_enabled(True)

    def disable_adapter(self) -> None:
        """Switches the adapter off: outputs are the base model's exactly (a merged adapter is unmerged first)."""
        self._core.set_adapter_enabled(False)

    def merge_adapter(self) -> None:
        """Adds the adapter into the base weights (faster sampling; unmerge_adapter restores them)."""
        self._core.merge_adapter()

    def unmerge_adapter(self) -> None:
        self._core.unmerge_adapter()

    def lift(self, image: ArrayLike, masks: Masks, *, pointmap: Optional[ArrayLike] = None,
             depth: Optional[ArrayLike] = None, K: Optional[Union[ArrayLike, Mapping[str, float]]] = None,
             crop_masks: Optional[Mapping[str, ArrayLike]] = None, seed: int = 0,
             preprocess: str = "model") -> LiftResult:
        """Lifts every object of one photo in one batched pass, as the ``lift`` program.

        image: uint8 RGB [H, W, 3] (as a file reads) or float [H, W, 3] in [0, 1].
        masks: a label map [H, W] of integers (ids ``label_<k>``), a dict {id: mask} or a list of masks
            (ids ``object_<i>``); each mask bool, uint8 (0/1 or 0/255) or float in [0, 1].
        pointmap: float [H, W, 3], OpenCV camera, inf/NaN invalid (MoGe's ``points``); K is then fitted
            to it unless given. depth: float metres [H, W] (needs K: a 3x3 matrix or {fx, fy, cx, cy}).
        preprocess: "model" (the model's own: the shipped miniature's sizes, else the released preset),
            "released", "default", or a YAML file of preprocessing keys.
        Per-object problems (empty mask, wrong size, no valid point) make that object not ok with an error
        naming it; the others are lifted. Whole-input problems raise InputError.
        """
        return LiftResult(self._core.lift(image, masks, pointmap=pointmap, depth=depth, K=K,
                                          crop_masks=crop_masks, seed=seed, preprocess=preprocess))

    def sample(self, cond: Union[torch.Tensor, Sequence[torch.Tensor]], *, seed: int = 0) -> List[List[Shape]]:
        """Stage-1 sampling on condition tokens [L, C] (one or a list): per condition, num_samples shapes."""
        conds = [cond] if isinstance(cond, torch.Tensor) else list(cond)
        return self._core.sample(conds, seed)

    def embed(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The condition embedder on its official inputs (image, rgb_image, mask, rgb_image_mask, pointmap,
        rgb_pointmap; preprocessed, [1, ...] or unbatched): condition tokens [L, C]."""
        return self._core.embed(dict(inputs))
