"""Graphs from a store, splits (shape, LOVO, source), the supervision ratio, and normalisation
fitted on the training split only."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from trainer.errors import TrainerError
from trainer.data.store_cases import build_training_data, read_store
from trainer.data.normalisation import Normalisation
from trainer.data.splits import make_split, parse_split, subsample_shapes, supervised_subset
from trainer_fixtures import make_tiny_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_tiny_store(tmp_path_factory.mktemp("trainer_data") / "tiny.zarr", shapes=5)


def test_shape_split_keeps_shapes_apart_and_is_seeded(store):
    cases = read_store(store)
    a = make_split(cases.keys, cases.params, "shape", seed=0)
    shapes = {name: {k[0] for k in keys} for name, keys in a.items()}
    assert shapes["train"] and shapes["test"]
    assert not (shapes["test"] & (shapes["train"] | shapes["val"]))  # no test shape is seen in training
    assert sorted(a["train"] + a["val"] + a["test"]) == cases.keys
    assert len(shapes["test"]) == 2  # round(0.3 × 5)
    assert make_split(cases.keys, cases.params, "shape", seed=0) == a
    assert any(make_split(cases.keys, cases.params, "shape", seed=s)["test"] != a["test"] for s in range(1, 6))
    # shape:F tests on the fraction F of the shapes (at least one); the rest train, as many as it allows
    small = make_split(cases.keys, cases.params, "shape:0.1", seed=0)
    assert len({k[0] for k in small["test"]}) == 1 and len(small["train"]) > len(a["train"])
    assert not ({k[0] for k in small["test"]} & {k[0] for k in small["train"] + small["val"]})
    assert make_split(cases.keys, cases.params, "shape:0.4", seed=0)["test"] == a["test"]  # round(0.4 × 5) = 2


def test_lovo_split_holds_out_one_value(store):
    cases = read_store(store)
    parts = make_split(cases.keys, cases.params, "lovo:P=12", seed=0)
    assert parts["test"] and all(cases.params[k][0] == 12.0 for k in parts["test"])
    assert all(cases.params[k][0] != 12.0 for k in parts["train"] + parts["val"])
    parts = make_split(cases.keys, cases.params, "lovo:C=200", seed=0)
    assert all(cases.params[k][1] == 200.0 for k in parts["test"])
    with pytest.raises(TrainerError, match="8, 12"):
        make_split(cases.keys, cases.params, "lovo:P=10", seed=0)


@pytest.mark.parametrize("spec", ["shapes", "lovo:", "lovo:Q=3", "lovo:P=abc", "lovo:P=nan", "kfold", "shape:0",
                                  "shape:1", "shape:x", "shape:nan"])
def test_bad_split_specs(spec):
    with pytest.raises(TrainerError):
        parse_split(spec)


def test_source_split_from_store_attrs(store):
    cases = read_store(store)
    attrs = {"splits": {"train": [0, 1, 2], "val": [3], "test": [4]}}
    parts = make_split(cases.keys, cases.params, "source", seed=0, store_attrs=attrs)
    assert {k[0] for k in parts["test"]} == {4} and {k[0] for k in parts["val"]} == {3}
    per_shape = {"shape_source_split": {0: "train", 1: "train", 2: "validation", 3: "test", 4: "test"}}
    parts = make_split(cases.keys, cases.params, "source", seed=0, store_attrs=per_shape)
    assert {k[0] for k in parts["test"]} == {3, 4} and {k[0] for k in parts["val"]} == {2}
    with pytest.raises(TrainerError, match="source"):
        make_split(cases.keys, cases.params, "source", seed=0, store_attrs={})


def test_graphs_hold_normalised_coordinates_targets_and_params(store):
    b = build_training_data(store, "shape", seed=0)
    cases = b.cases
    g = b.test[0]
    key = tuple(g.key[0].tolist())
    feat = cases.features[key[0]]
    np.testing.assert_allclose(g.x.numpy(), b.norm.coords(feat.ed_mm, feat.base_nodes), atol=1e-5)
    np.testing.assert_allclose(g.y.numpy() * b.norm.disp_scale_mm, cases.unloaded[key] - feat.ed_mm, atol=1e-5)
    assert g.params.shape == (1, 4)
    p = g.params[0].numpy()
    assert p[0] in (0.0, 1.0) and p[1] in (0.0, 1.0) and p[2] == 0.0 and p[3] == 0.0  # grid bounds → [0, 1]
    assert g.edge_index.shape[0] == 2 and int(g.edge_index.max()) < g.num_nodes
    assert set(g.region.unique().tolist()) <= set(range(6)) and len(g.region.unique()) >= 4


def test_normalisation_uses_the_training_split_only(store):
    b = build_training_data(store, "shape", seed=0)
    c = b.cases
    from trainer.data.normalisation import placed_nodes

    train_ed = [placed_nodes(c.features[k[0]].ed_mm, c.features[k[0]].base_nodes) for k in b.split["train"]]
    every_ed = [placed_nodes(c.features[k[0]].ed_mm, c.features[k[0]].base_nodes) for k in c.keys]
    train_disp = [c.unloaded[k] - c.features[k[0]].ed_mm for k in b.split["train"]]
    expected = Normalisation.fit(train_ed, train_disp, c.attrs["grid"])
    np.testing.assert_allclose(b.norm.centre_mm, expected.centre_mm, rtol=0, atol=1e-12)
    assert b.norm.scale_mm == pytest.approx(expected.scale_mm, rel=1e-12)
    assert b.norm.disp_scale_mm == pytest.approx(expected.disp_scale_mm, rel=1e-12)
    including_test = Normalisation.fit(every_ed, train_disp, c.attrs["grid"])
    assert np.abs(np.subtract(including_test.centre_mm, b.norm.centre_mm)).max() > 1e-3  # it would differ


def test_supervision_ratio_really_removes_labels(store):
    full = build_training_data(store, "shape", seed=0, sr=1.0)
    b = build_training_data(store, "shape", seed=0, sr=0.25)
    n = len(b.split["train"])
    assert len(b.labelled) == max(1, round(0.25 * n)) < n
    assert b.labelled == supervised_subset(b.split["train"], 0.25, 0)
    for g in b.train:
        key = tuple(g.key[0].tolist())
        if key in b.labelled:
            assert bool(g.labelled) and torch.isfinite(g.y).all()
        else:
            assert not bool(g.labelled) and torch.isnan(g.y).all()  # the label is gone, not just flagged
    assert all(bool(g.labelled) and torch.isfinite(g.y).all() for g in b.val + b.test)
    # the displacement scale comes from the labelled cases only
    c = b.cases
    d = np.concatenate([c.unloaded[k] - c.features[k[0]].ed_mm for k in sorted(b.labelled)])
    assert b.norm.disp_scale_mm == pytest.approx(float(np.sqrt((d ** 2).mean())), rel=1e-12)
    assert b.norm.disp_scale_mm != pytest.approx(full.norm.disp_scale_mm, rel=1e-9)
    with pytest.raises(TrainerError):
        from trainer.config import TrainConfig

        TrainConfig(store=store, sr=0.0)


def test_label_seed_draws_other_labels_on_the_same_split(store):
    """--label-seed: another labelled subset of the same size; split and test cases unchanged."""
    from trainer.config import TrainConfig
    from trainer.training.loop import check_same_run

    default = build_training_data(store, "shape", seed=0, sr=0.25)
    same = build_training_data(store, "shape", seed=0, sr=0.25, label_seed=0)
    other = build_training_data(store, "shape", seed=0, sr=0.25, label_seed=1)
    assert same.labelled == default.labelled
    assert other.split == default.split and len(other.labelled) == len(default.labelled)
    assert other.labelled != default.labelled and other.labelled <= set(other.split["train"])
    assert other.labelled == supervised_subset(other.split["train"], 0.25, 1)
    cfg = TrainConfig(store=store, sr=0.25, split_seed=0, label_seed=1)
    assert cfg.labels_seed == 1 and cfg.data_seed == 0
    # naming the default label seed keeps a run's identity; another one refuses to resume it
    old = TrainConfig(store=store, sr=0.25)
    assert TrainConfig(store=store, sr=0.25, label_seed=0).identity() == old.identity()
    with pytest.raises(TrainerError, match="label_seed"):
        check_same_run({"train_config": old.as_dict()}, cfg, "runs/x")
    with pytest.raises(TrainerError, match="label_seed"):
        check_same_run({"train_config": cfg.as_dict()}, old, "runs/x")
    with pytest.raises(TrainerError, match="needs `sr`"):
        TrainConfig(store=store, label_seed=1)
    with pytest.raises(TrainerError, match="`label_seed`"):
        TrainConfig(store=store, sr=0.25, label_seed=-1)


def test_train_fraction_keeps_whole_nested_training_shapes(store):
    """--train-fraction: whole training shapes are dropped (never val or test ones), at least one
    shape stays, a smaller fraction keeps a subset of a larger one's shapes, and the normalisation
    follows the kept training cases."""
    full = build_training_data(store, "lovo:P=12", seed=0)
    train_shapes = sorted({k[0] for k in full.split["train"]})
    assert len(train_shapes) == 5
    kept = {}
    for f in (0.2, 0.6, 1.0):
        b = build_training_data(store, "lovo:P=12", seed=0, train_fraction=f)
        assert b.split["val"] == full.split["val"] and b.split["test"] == full.split["test"]
        kept[f] = {k[0] for k in b.split["train"]}
        assert len(kept[f]) == max(1, round(f * 5))
        assert b.split["train"] == [k for k in full.split["train"] if k[0] in kept[f]]  # whole shapes
    assert kept[0.2] < kept[0.6] < kept[1.0]
    small = build_training_data(store, "lovo:P=12", seed=0, train_fraction=0.2)
    assert len(small.train) == len(small.split["train"]) and small.norm.scale_mm != full.norm.scale_mm
    assert subsample_shapes(full.split["train"], 0.01, 0) and subsample_shapes([], 0.5, 0) == []
    from trainer.config import TrainConfig

    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(TrainerError, match="`train_fraction`"):
            TrainConfig(store="s", train_fraction=bad)
    assert TrainConfig(store="s").identity() != TrainConfig(store="s", train_fraction=0.5).identity()


def test_normalisation_is_fitted_and_applied_in_the_training_frame(store):
    """Meshes lying anywhere: the fitted scale is that of the placed meshes, and a moved mesh gets the
    same network input as where it lay."""
    from trainer.data.normalisation import Normalisation, placed_nodes

    b = build_training_data(store, "shape", seed=0)
    key = b.split["train"][0]
    feat = b.cases.features[key[0]]
    shift = np.array([40.0, -25.0, 12.0])
    np.testing.assert_allclose(b.norm.coords(feat.ed_mm + shift, feat.base_nodes),
                               b.norm.coords(feat.ed_mm, feat.base_nodes), atol=1e-12)
    placed = placed_nodes(feat.ed_mm + shift, feat.base_nodes)
    assert abs(placed[:, :2].mean(axis=0)).max() < 1e-9 and abs(placed[feat.base_nodes, 2].mean()) < 1e-9
    here = Normalisation.fit([placed_nodes(feat.ed_mm, feat.base_nodes)], [], b.cases.attrs["grid"])
    scattered = [placed_nodes(feat.ed_mm + k * shift, feat.base_nodes) for k in range(3)]
    assert Normalisation.fit(scattered, [], b.cases.attrs["grid"]).scale_mm == pytest.approx(here.scale_mm, rel=1e-9)
