"""Package a trained run as the network shipped with heartctl (trainer/shipped/): half-precision
weights, its trade table, and a manifest of digests with what it was trained on and the largest
change half precision makes on held-out meshes.

    .venv/bin/python scripts/ship_network.py RUN_DIR [TRADE_DIR]
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from solver.meshing import mesh_lv  # noqa: E402
from solver.shape_model import lv_shape  # noqa: E402
from trainer.training.checkpoint import load_run  # noqa: E402
from trainer.data.features import mesh_features  # noqa: E402
from trainer.shipped import NETWORK, half_precision_error_mm, package_run, record  # noqa: E402

BUNDLED = Path(__file__).resolve().parents[1] / "tests" / "data" / "shipped_reference_pairs.npz"


def bundled_pairs_mean_mm(run: Path) -> float:
    """The network's mean node error on the bundled reference pairs (scripts/bundle_reference_pairs.py)."""
    from solver.mesh import make_mesh
    from solver.parameters import CaseParameters
    from trainer.evaluation.predict import unload_with_network

    data = np.load(BUNDLED)
    errors = []
    for i in range(int(data["count"])):
        mesh = make_mesh(*(data[f"{i}_{k}"].astype(np.int64) if k != "nodes" else data[f"{i}_{k}"]
                           for k in ("nodes", "tets", "endo", "epi", "base")))
        out = unload_with_network(mesh, CaseParameters(*data[f"{i}_params"]), [run])
        errors.append(float(np.linalg.norm(out.unloaded_nodes - data[f"{i}_reference"], axis=1).mean()))
    return float(np.mean(errors))


def main(run_dir: Path, trade_dir: Path | None) -> None:
    state = load_run(run_dir)
    fp, cfg = state["fingerprint"], state["train_config"]
    parent = cfg.get("init_from")
    card = {"configuration": cfg["config_name"], "fine_tuned_from": Path(parent).parent.name if parent else None,
            "store": {k: fp.get(k) for k in ("grid", "fidelity", "seed", "base", "fibres", "mesh_nodes",
                                             "shape_model_version")},
            "best_epoch": state.get("best_epoch"), "training_shapes": len(state["train_descriptors"].get("shapes", []))}
    manifest = package_run(run_dir, trade_dir, card)
    grid = fp["grid"]
    params = np.array([np.mean(grid[a]) for a in ("pressure_mmhg", "stiffness_pa", "helix_endo_deg", "helix_epi_deg")])
    items = [(mesh_features(mesh_lv(lv_shape(s, 0, 2), 350)), params, None) for s in (20, 21)]
    error = half_precision_error_mm(run_dir, NETWORK, items)
    manifest = record({"half_precision_max_change_mm": error, "bundled_pairs_mean_mm": bundled_pairs_mean_mm(NETWORK)})
    print(f"packaged {run_dir} into {NETWORK}: {manifest['bytes'] / 2**20:.2f} MB, {manifest['parameters']:,} "
          f"parameters in float16 (largest change from float32 on held-out shapes 20, 21: {error:.2e} mm); "
          f"{manifest['bundled_pairs_mean_mm']:.3f} mm mean node error on the bundled reference pairs")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else None)
