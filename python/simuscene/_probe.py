"""The physics probe on a Scene: decisions, metrics, the final scene, MJCF and pictures."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import numpy as np

from . import _core
from ._core import Scene
from ._stage1 import Stage1

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["probe", "ProbeResult", "ProbeDecision", "Candidate"]


@dataclass(frozen=True)
class Candidate:
    """One resampled shape tried for an object (best-of-N) and how stable it was."""

    label: str
    ok: bool
    displacement: float  # m: penetration push + settle motion
    rotation_deg: float
    penetration: float  # m: deepest contact where it was placed
    message: str  # why not ok
    chosen: bool


@dataclass(frozen=True)
class ProbeDecision:
    """What the probe decided for one object (report.json's entry; ``raw`` holds all of it)."""

    id: str
    branch: str  # none | stretch | resample | anchored | disabled
    rho: float
    flags: List[str]
    message: str
    displacement: Optional[float]  # m in the evaluation settle of the final scene (None: not simulated)
    displacement_before: Optional[float]  # m, the input scene settled the same way
    resampled: bool
    candidates: List[Candidate] = field(default_factory=list)
    raw: Dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def from_report(entry: Dict[str, Any]) -> "ProbeDecision":
        def moved(rec: Optional[Dict[str, Any]]) -> Optional[float]:
            if rec is None or rec.get("physics_disabled"):
                return None
            return float(rec["displacement"])

        rs = entry.get("resample", {})
        cands = [Candidate(c["label"], c["ok"], c["displacement"], c["rotation_deg"], c["penetration"], c["message"],
                           c["chosen"]) for c in rs.get("candidates", [])]
        return ProbeDecision(entry["id"], entry["branch"], float(entry["rho"]), list(entry["flags"]), entry["message"],
                             moved(entry.get("evaluation")), moved(entry.get("evaluation_input")),
                             bool(rs.get("resampled", False)), cands, entry)


class ProbeResult:
    """What probe() returns.

    report: report.json's content (dict). decisions: one ProbeDecision per object (scene order).
    metrics: the headline metrics {"before": ..., "after": ...}; metrics_table: the same as text.
    scene: the corrected Scene. meshes: per object the canonical mesh (vertices, faces) it ends with, or
    None. mjcf: the final MJCF text (its visual meshes are ``meshes/<id>.obj`` beside ``mjcf_path``, written
    only with ``out``). pictures: name -> RGB uint8 [H, W, 3] (the PNGs the probe wrote; empty without ``out``).
    """

    def __init__(self, run: _core.ProbeRun) -> None:
        self._run = run
        self.report: Dict[str, Any] = json.loads(run.report_json)
        self.decisions: List[ProbeDecision] = [ProbeDecision.from_report(e) for e in self.report["objects"]]
        self.metrics: Dict[str, Any] = {"before": run.headline_before, "after": run.headline_after}
        self.metrics_table: str = run.metrics_table
        self.summary: str = run.summary
        self.scene: Scene = run.scene
        self.mjcf: str = run.mjcf
        self.out_dir: Optional[str] = run.out_dir or None

    @property
    def meshes(self) -> List[Optional[Tuple[np.ndarray, np.ndarray]]]:
        return [self._run.mesh(i) for i in range(len(self.decisions))]

    @property
    def mjcf_path(self) -> Optional[str]:
        """scene.xml in ``out`` (None when nothing was written)."""
        if self.out_dir is None:
            return None
        p = os.path.join(self.out_dir, "scene.xml")
        return p if os.path.exists(p) else None

    @property
    def pictures(self) -> Dict[str, np.ndarray]:
        return {k: v for k, v in self._run.pictures.items() if v is not None}

    def decision(self, object_id: str) -> ProbeDecision:
        for d in self.decisions:
            if d.id == object_id:
                return d
        raise KeyError(f"no object '{object_id}' in the probe result")


def probe(scene: Scene, *, config: Optional[PathLike] = None, overrides: Optional[Mapping[str, Any]] = None,
          out: Optional[PathLike] = None, overwrite: bool = False, resampler: Optional[Stage1] = None, seed: int = 0,
          preprocess: str = "model") -> ProbeResult:
    """Runs the physics probe (the ``probe`` program's work) on ``scene``.

    config: a probe YAML (configs/probe.yaml; None = the built-in defaults); overrides: {"key.path": value}
    as the program's --set. out: a folder for scene.json, meshes/, scene.xml, report.json and the pictures
    (refused when it exists unless overwrite). resampler: a Stage1 with a condition embedder resamples the
    objects whose rho crosses the threshold in-process (as --resample); None writes the hand-off instead.
    Releases the GIL; several threads may probe at once.
    """
    run = _core.probe(scene, config=config, overrides=None if overrides is None else dict(overrides), out=out,
                      overwrite=overwrite, resampler=None if resampler is None else resampler._core, seed=seed,
                      preprocess=preprocess)
    return ProbeResult(run)
