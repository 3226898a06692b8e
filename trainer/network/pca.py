"""The PCA displacement baseline: each displacement field expressed in one smooth basis over the LV
wall (ζ base–apex, τ transmural, θ circumferential), PCA of the training ones, PCA coefficients
regressed (ridge) from features of the parameters and of the ED shape's own PCA scores.

The features are quadratic in the scaled parameters p̂, linear in the shape scores s, plus the
products p̂_i·s_j (how a shape gives depends on the load). Not quadratic in (p̂, s) together: with
36 training shapes the 36 shape-only quadratic terms interpolate the training shapes and extrapolate
badly (60-shape paper grid: test MD 1.18 mm, no better than the mean
displacement, against 0.29 mm on the training cases). The ridge weight is chosen on the validation
cases when they are given."""
from __future__ import annotations

import numpy as np
import torch

from trainer.errors import TrainerError
from trainer.data.features import MeshFeatures
from trainer.data.normalisation import Normalisation

N_ZETA, N_TAU, N_FOURIER = 7, 3, 4  # Legendre degrees < 7 in ζ, < 3 in τ; Fourier modes ≤ 4 in θ
FIT_RIDGE = 1e-4  # relative Tikhonov weight of the per-mesh least-squares fit
RIDGE_GRID = (1e-3, 1e-2, 1e-1, 1.0)  # regression ridge weights tried on the validation cases
FEATURE_MAP = 2  # the feature map's version, kept in the fitted state (1: quadratic in shape scores too)


def wall_basis(feat: MeshFeatures) -> np.ndarray:
    """[n, 7·3·9] smooth basis over the wall: P_i(2ζ−1) · P_j(2τ−1) · {1, cos mθ, sin mθ}, θ about the
    long axis through the mesh's (x, y) centroid. The same functions on every mesh, so coefficient
    vectors of different meshes are comparable."""
    from numpy.polynomial import legendre

    xy = feat.ed_mm[:, :2] - feat.ed_mm[:, :2].mean(axis=0)
    th = np.arctan2(xy[:, 1], xy[:, 0])
    Z = legendre.legvander(2 * np.asarray(feat.zeta) - 1, N_ZETA - 1)
    T = legendre.legvander(2 * np.asarray(feat.tau) - 1, N_TAU - 1)
    F = np.concatenate([np.ones((len(th), 1))] + [np.stack([np.cos(m * th), np.sin(m * th)], axis=1)
                                                  for m in range(1, N_FOURIER + 1)], axis=1)
    return np.einsum("ni,nj,nk->nijk", Z, T, F).reshape(len(th), -1)


def resampling(feat: MeshFeatures) -> tuple[np.ndarray, np.ndarray]:
    """(Fit [p,n], Φ [n,p]): nodal field → basis coefficients (ridge least squares) and back."""
    phi = wall_basis(feat)
    G = phi.T @ phi
    lam = FIT_RIDGE * np.trace(G) / G.shape[0]
    return np.linalg.solve(G + lam * np.eye(G.shape[0]), phi.T), phi


def _quadratic(f: np.ndarray) -> np.ndarray:
    iu = np.triu_indices(f.shape[1])
    return np.concatenate([f, (f[:, :, None] * f[:, None, :])[:, iu[0], iu[1]]], axis=1)


FITTED_KEYS = ("disp_mean", "disp_comps", "shape_mean", "shape_comps", "shape_sd", "feat_mean", "feat_sd",
               "ridge_w", "ridge_b")  # what predict reads


class PCABaseline:
    """Fitted state as plain arrays (saved as tensors in the checkpoint)."""

    @classmethod
    def from_checkpoint(cls, state: dict) -> "PCABaseline":
        """A fitted baseline from a checkpoint's weights; TrainerError (one line) if parts are missing."""
        missing = [k for k in FITTED_KEYS if k not in state]
        if missing:
            raise TrainerError(f"checkpoint is damaged: the PCA baseline lacks {', '.join(missing)}")
        return cls(state)

    def __init__(self, state: dict):
        self.s = {k: np.asarray(v.cpu().numpy() if isinstance(v, torch.Tensor) else v, dtype=np.float64)
                  for k, v in state.items()}
        if "ridge_w" in self.s and float(np.ravel(self.s.get("feature_map", 1.0))[0]) != FEATURE_MAP:
            raise TrainerError("this PCA baseline was fitted with an older feature map; "
                               "refit it (heartctl train `config` pca, seconds)")
        self._cache: dict = {}

    @classmethod
    def fit(cls, features: dict, keys: list, params: dict, displacements: dict, norm: Normalisation,
            n_components: int = 16, ridge: float = 1e-2, validation: dict | None = None) -> "PCABaseline":
        """features: shape → MeshFeatures; keys: labelled training cases; params and unloading
        displacements (X − x_ED, mm) by key. validation: unloading displacements of validation
        cases by key (their params in `params`); when given, the ridge weight is the one of
        RIDGE_GRID with the lowest validation MD, not `ridge`."""
        shapes = sorted({k[0] for k in keys})
        rs = {s: resampling(features[s]) for s in shapes}
        desc = {s: (rs[s][0] @ norm.coords(*features[s].coords_placed)).ravel() for s in shapes}
        D = np.stack([(rs[k[0]][0] @ displacements[k]).ravel() for k in keys])
        d_mean = D.mean(axis=0)
        _, _, Vt = np.linalg.svd(D - d_mean, full_matrices=False)
        m = max(1, min(n_components, len(keys) - 1, Vt.shape[0]))
        comps = Vt[:m]
        coef = (D - d_mean) @ comps.T
        S = np.stack([desc[s] for s in shapes])
        s_mean = S.mean(axis=0)
        ms = max(0, min(8, len(shapes) - 1))
        if ms:
            _, sv, sVt = np.linalg.svd(S - s_mean, full_matrices=False)
            s_comps = sVt[:ms]
            s_sd = np.maximum(sv[:ms] / np.sqrt(max(len(shapes) - 1, 1)), 1e-9)
        else:
            s_comps, s_sd = np.zeros((0, S.shape[1])), np.zeros(0)
        state = {"disp_mean": d_mean, "disp_comps": comps, "shape_mean": s_mean, "shape_comps": s_comps,
                 "shape_sd": s_sd}
        model = cls(state)
        F = np.stack([model._features(desc[k[0]], norm.params(params[k])) for k in keys])
        f_mean, f_sd = F.mean(axis=0), np.maximum(F.std(axis=0), 1e-9)
        Fz = (F - f_mean) / f_sd
        c_mean = coef.mean(axis=0)
        gram, rhs = Fz.T @ Fz, Fz.T @ (coef - c_mean)

        def ridge_weights(r: float) -> np.ndarray:
            return np.linalg.solve(gram + r * len(keys) * np.eye(gram.shape[0]), rhs)

        model.s.update({"feat_mean": f_mean, "feat_sd": f_sd, "ridge_b": c_mean,
                        "feature_map": np.array(float(FEATURE_MAP))})
        if validation:
            val_md = {}
            for r in RIDGE_GRID:
                model.s["ridge_w"] = ridge_weights(r)
                val_md[r] = model.mean_distance_mm(features, params, validation, norm)
            ridge = min(val_md, key=val_md.get)
        model.s.update({"ridge_w": ridge_weights(ridge), "ridge": np.array(float(ridge))})
        return model

    def mean_distance_mm(self, features: dict, params: dict, displacements: dict, norm: Normalisation) -> float:
        """MD (mm): the mean over cases of the mean nodal distance between predicted and given displacements."""
        return float(np.mean([np.linalg.norm(self.predict(features[k[0]], params[k], norm, cache_key=k[0]) - d,
                                             axis=1).mean() for k, d in displacements.items()]))

    def _features(self, desc: np.ndarray, p_hat: np.ndarray) -> np.ndarray:
        """Quadratic in p̂ [4], linear in the shape scores s, and every product p̂_i·s_j."""
        sc = (desc - self.s["shape_mean"]) @ self.s["shape_comps"].T / self.s["shape_sd"] if len(self.s["shape_sd"]) \
            else np.zeros(0)
        p_hat = np.asarray(p_hat, dtype=np.float64)
        return np.concatenate([_quadratic(p_hat[None])[0], sc, np.outer(p_hat, sc).ravel()])

    def predict(self, feat: MeshFeatures, params, norm: Normalisation, cache_key=None) -> np.ndarray:
        """Unloading displacement X − x_ED, mm, [n,3]."""
        if cache_key is not None and cache_key in self._cache:
            S, R = self._cache[cache_key]
        else:
            S, R = resampling(feat)
            if cache_key is not None:
                self._cache[cache_key] = (S, R)
        desc = (S @ norm.coords(*feat.coords_placed)).ravel()
        f = (self._features(desc, norm.params(params)) - self.s["feat_mean"]) / self.s["feat_sd"]
        coef = f @ self.s["ridge_w"] + self.s["ridge_b"]
        D = (self.s["disp_mean"] + coef @ self.s["disp_comps"]).reshape(-1, 3)
        return R @ D

    def state_dict(self) -> dict:
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in self.s.items()}
