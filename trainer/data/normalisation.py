"""The network's units: coordinates centred and scaled, the unloading displacement scaled, and the
parameters mapped to [0, 1] over the training box, with the load features and the fitted size of a
case's displacement (fit_load_scale). Fitted on the training split only (trainer.data.store_cases)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from storage.schema import PARAM_NAMES

from trainer.errors import TrainerError


def load_features(p_hat, box):
    """[B, 8] regressors of a case's displacement size from its normalised parameters p̂ [B, 4]
    (NumPy or torch; clipped to the grid box [0, 1]): 1, ln P, ln C, (ln P)², (ln C)², ln P · ln C,
    θ̂endo, θ̂epi, with P (mmHg) and C (Pa) recovered from p̂ by box = (P_lo, C_lo, P_hi, C_hi)."""
    if isinstance(p_hat, torch.Tensor):
        p, stack, log = p_hat.clamp(0.0, 1.0), torch.stack, torch.log
    else:
        p, stack, log = np.clip(np.asarray(p_hat, dtype=np.float64), 0.0, 1.0), np.stack, np.log
    lo_p, lo_c, hi_p, hi_c = (float(v) for v in box)
    P = log(lo_p + p[:, 0] * (hi_p - lo_p) + 1e-9)
    C = log(lo_c + p[:, 1] * (hi_c - lo_c) + 1e-9)
    return stack([P * 0 + 1, P, C, P * P, C * C, P * C, p[:, 2], p[:, 3]], 1)


N_LOAD_FEATURES = 8
LOAD_RIDGE = 1e-6  # on the non-constant regressors of the displacement-size fit: only to keep it well posed


def fit_load_scale(p_hat: np.ndarray, box, rms_mm: np.ndarray, disp_scale_mm: float) -> tuple:
    """Coefficients a of log(rms / disp_scale) ≈ load_features(p̂, box) · a: the typical size of a case's
    unloading displacement from its loading (pressure, stiffness; helix angles linearly), fitted by
    ridge least squares on the labelled training cases' RMS displacement (mm)."""
    A = load_features(p_hat, box)
    b = np.log(np.maximum(np.asarray(rms_mm, dtype=np.float64), 1e-9) / disp_scale_mm)
    reg = np.diag([0.0] + [LOAD_RIDGE] * (A.shape[1] - 1)) * len(b)
    coef = np.linalg.solve(A.T @ A + reg + 1e-12 * np.eye(A.shape[1]), A.T @ b)
    return tuple(float(v) for v in coef)


def placed_nodes(nodes_mm: np.ndarray, base_nodes: np.ndarray) -> np.ndarray:
    """A mesh's nodes (mm) moved so that their centroid lies on the z axis and the base plane (mean z
    of the base nodes) at z = 0: the frame the generator makes meshes in, whatever the input's placement."""
    x = np.asarray(nodes_mm, dtype=np.float64)
    return x - np.array([*x[:, :2].mean(axis=0), x[np.asarray(base_nodes), 2].mean()])


@dataclass(frozen=True)
class Normalisation:
    """x̂ = (x − centre) / scale for coordinates (mm); ŷ = (X − x) / disp_scale for the unloading
    displacement (mm); p̂ = (p − lo) / (hi − lo) per parameter, lo/hi the store grid's bounds (an axis
    with one value maps to 0); load_coef: log of a case's expected displacement size (in disp_scale
    units) as load_features(p̂) · load_coef (fit_load_scale; () when not fitted). Fitted on the
    training split only."""

    centre_mm: tuple
    scale_mm: float
    disp_scale_mm: float
    param_lo: tuple
    param_hi: tuple
    load_coef: tuple = ()

    @property
    def load_box(self) -> tuple:
        """(P_lo, C_lo, P_hi, C_hi): the grid's pressure (mmHg) and stiffness (Pa) bounds, for load_features."""
        return (float(self.param_lo[0]), float(self.param_lo[1]), float(self.param_hi[0]), float(self.param_hi[1]))

    @property
    def disp_to_coord(self) -> float:
        """A normalised displacement expressed in normalised coordinates (disp_scale / scale)."""
        return self.disp_scale_mm / self.scale_mm

    def coords(self, nodes_mm: np.ndarray, base_nodes: np.ndarray | None = None) -> np.ndarray:
        """Normalised coordinates x̂ = (x − centre) / scale. With `base_nodes` (indices of the mesh's
        base surface nodes) the mesh is first placed in the training frame, whatever its placement
        (placed_nodes: node centroid on the z axis, base plane at z = 0, the frame every generated
        mesh is made in, docs/data.md), and x̂ = (placed − (0, 0, centre_z)) / scale. The FE answer does
        not depend on where a mesh lies; placed, neither does the network's. A generated mesh moves by
        its centroid's distance from the axis (< 1 mm)."""
        centre = np.asarray(self.centre_mm, dtype=np.float64)
        if base_nodes is not None and len(base_nodes):
            return (placed_nodes(nodes_mm, base_nodes) - np.array([0.0, 0.0, centre[2]])) / self.scale_mm
        return (np.asarray(nodes_mm, dtype=np.float64) - centre) / self.scale_mm

    def params(self, values) -> np.ndarray:
        lo, hi = np.asarray(self.param_lo), np.asarray(self.param_hi)
        span = np.where(hi > lo, hi - lo, 1.0)
        return np.where(hi > lo, (np.asarray(values, dtype=np.float64) - lo) / span, 0.0)

    def as_dict(self) -> dict:
        return {"centre_mm": [float(v) for v in self.centre_mm], "scale_mm": float(self.scale_mm),
                "disp_scale_mm": float(self.disp_scale_mm), "param_lo": [float(v) for v in self.param_lo],
                "param_hi": [float(v) for v in self.param_hi], "load_coef": [float(v) for v in self.load_coef]}

    @classmethod
    def from_dict(cls, d: dict) -> "Normalisation":
        return cls(tuple(d["centre_mm"]), float(d["scale_mm"]), float(d["disp_scale_mm"]), tuple(d["param_lo"]),
                   tuple(d["param_hi"]), tuple(d.get("load_coef", ())))

    @classmethod
    def fit(cls, ed_nodes: list, displacements: list, grid: dict, params: list | None = None) -> "Normalisation":
        """ed_nodes: the ED node arrays of the training cases (placed_nodes: the frame coords works in,
        so that meshes lying anywhere do not inflate the scale); displacements: unloaded − ED of the
        labelled training cases (mm); grid: the store's parameter axes; params: the labelled cases'
        parameters [4] (in `displacements` order), to fit load_coef (None: not fitted)."""
        allx = np.concatenate([np.asarray(x, dtype=np.float64) for x in ed_nodes])
        centre = allx.mean(axis=0)
        scale = float(np.sqrt(((allx - centre) ** 2).sum(axis=1).mean()))
        d = np.concatenate([np.asarray(u, dtype=np.float64) for u in displacements]) if displacements else np.zeros((1, 3))
        disp_scale = float(np.sqrt((d**2).mean()))
        if not (scale > 0 and math.isfinite(scale)):
            raise TrainerError("training ED coordinates have no spread; cannot normalise")
        if not (disp_scale > 1e-9 and math.isfinite(disp_scale)):
            disp_scale = 1.0
        lo = tuple(float(min(grid[a])) for a in PARAM_NAMES)
        hi = tuple(float(max(grid[a])) for a in PARAM_NAMES)
        norm = cls(tuple(float(v) for v in centre), scale, disp_scale, lo, hi)
        if params is None or not displacements:
            return norm
        rms = [float(np.sqrt(np.mean(np.asarray(u, dtype=np.float64) ** 2))) for u in displacements]
        p_hat = np.stack([norm.params(p) for p in params])
        return replace(norm, load_coef=fit_load_scale(p_hat, norm.load_box, rms, disp_scale))
