"""Configurations: a base name plus options (--node-input, --ema, --dropout, --output-scale, --layer,
--set) give the networks the compatibility names stand for, field by field; the recommended preset;
--set reads each field's type and refuses unknown keys; the one-line description."""
from __future__ import annotations

from dataclasses import fields, replace

import pytest

from trainer.config import (ALIASES, BASE_CONFIGS, CODES, PAPER, ModelConfig, TrainConfig, canonical_name, code_of,
                            compose, describe_model, describe_run, named_config)
from trainer.errors import TrainerError

# the compatibility names' networks, spelt out field by field as trainer/config.py defines them
_RESP = dict(cycle=False, ema_decay=0.99, node_features="wall-response", dropout=0.0)
SPELT_OUT = {
    "A1ema": replace(PAPER, cycle=False, ema_decay=0.99),
    "A1ema-wall": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall"),
    "A1ema-wall-d0": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall", dropout=0.0),
    "A1ema-wall-d0-load": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall", dropout=0.0,
                                  output_scale="load"),
    "A1ema-resp-d0": replace(PAPER, **_RESP),
    "A1ema-resp-d0-load": replace(PAPER, **_RESP, output_scale="load"),
    "A1ema-resp-d0-gcn": replace(PAPER, **_RESP, conv="gcn"),
    "R5-resp-d0": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=2, cycle_grad="teacher", lambda_cycle=1.0,
                          ema_decay=0.99, node_features="wall-response", dropout=0.0),
}
# the same networks as train options
AS_OPTIONS = {
    "A1ema": ("no-cycle", dict(ema=0.99)),
    "A1ema-wall": ("A1", dict(ema=0.99, node_input="wall")),
    "A1ema-wall-d0": ("no-cycle", dict(ema=0.99, node_input="wall", dropout=0)),
    "A1ema-wall-d0-load": ("paper", dict(ema=0.99, node_input="wall", dropout=0, output_scale="load",
                                         settings=["cycle=false"])),
    "A1ema-resp-d0": ("paper", dict(node_input="response", ema=0.99, dropout=0, settings=["cycle=false"])),
    "A1ema-resp-d0-load": ("A1", dict(node_input="response", ema=0.99, dropout=0, output_scale="load")),
    "A1ema-resp-d0-gcn": ("no-cycle", dict(node_input="response", ema=0.99, dropout=0, layer="gcn")),
    "R5-resp-d0": ("mean-teacher", dict(node_input="response", dropout=0, settings=["cycle-rampup-epochs=2"])),
}


@pytest.mark.parametrize("name", sorted(AS_OPTIONS))
def test_options_compose_the_networks_of_the_compatibility_names(name):
    base, options = AS_OPTIONS[name]
    model, training = compose(base, **options)
    for f in fields(ModelConfig):
        assert getattr(model, f.name) == getattr(SPELT_OUT[name], f.name), f.name
    assert named_config(name) == model == compose(name)[0] and training == {}
    assert named_config(name.upper()) == model  # names are case-insensitive


def test_every_compatibility_name_is_spelt_out_here():
    assert set(ALIASES) - set(CODES) == set(SPELT_OUT) == set(AS_OPTIONS)


def test_each_code_is_its_named_network():
    """A1 … R5 give the networks of their descriptive names, which every description uses."""
    assert set(CODES.values()) <= set(BASE_CONFIGS) and not set(CODES) & set(BASE_CONFIGS)
    for code, name in CODES.items():
        assert named_config(code) == named_config(code.lower()) == BASE_CONFIGS[name]
        assert canonical_name(code) == name and code_of(name) == code_of(code) == code
        assert describe_model(named_config(code)) == name
    assert canonical_name("A1ema") == "A1ema" and code_of("paper") == ""


def test_recommended_is_the_response_network_with_its_recipe():
    model, training = compose("recommended")
    assert model == SPELT_OUT["A1ema-resp-d0"]
    assert training == {"scale_pct": 8.0, "lr_schedule": "cosine"}
    cfg = TrainConfig(store="s.zarr", model=model, **training)
    assert describe_run(cfg) == ("recommended = no-cycle + node-input response, ema 0.99, dropout 0; "
                                 "scale-pct 8, lr-schedule cosine")
    assert describe_run(replace(cfg, scale_pct=4.0)).startswith("no-cycle + node-input response")  # not the preset's
    assert compose("recommended", ema=0.0)[0].ema_decay == 0.0  # an option changes a preset too


def test_set_reads_each_fields_type_and_is_applied_last():
    model, training = compose("paper", ema=0.5, settings=["hidden=64", "decoder_hidden=64,32", "cycle=no",
                                                           "ema_decay=0.9", "weight-decay=1e-5", "lambda_cycle=0.5"])
    assert (model.hidden, model.decoder_hidden, model.cycle, model.ema_decay, model.lambda_cycle) == \
        (64, (64, 32), False, 0.9, 0.5)
    assert training == {"weight_decay": 1e-5}
    assert describe_model(model) == "no-cycle + ema 0.9, hidden=64, lambda_cycle=0.5, decoder_hidden=64,32"


@pytest.mark.parametrize("settings,words", [
    (["hiden=8"], "unknown `set` key 'hiden'"),
    (["scale_pct=8"], "unknown `set` key 'scale_pct'"),  # it has an option of its own
    (["hidden"], "`set` takes key=value"),
    (["hidden=1.5"], "hidden takes an integer"),
    (["cycle=maybe"], "cycle takes true or false"),
    (["lambda_cycle=inf"], "lambda_cycle takes a finite number"),
    (["decoder_hidden=0"], "must be ≥ 1"),
    (["conv=mlp"], "model conv must be one of"),
    (["dropout=1"], "dropout must be in [0, 1)"),
])
def test_bad_settings_are_one_line(settings, words):
    with pytest.raises(TrainerError) as err:
        model, training = compose("paper", settings=settings)
        TrainConfig(store="s.zarr", model=model, **training)
    assert words in str(err.value) and "\n" not in str(err.value)


def test_a_train_config_without_network_settings_resolves_its_name():
    d = TrainConfig(store="s.zarr", config_name="A1ema-resp-d0").as_dict()
    d.pop("model")
    assert TrainConfig.from_dict(d).model == SPELT_OUT["A1ema-resp-d0"]
    with pytest.raises(TrainerError, match="'B7' lists no network settings"):
        TrainConfig.from_dict({**d, "config_name": "B7"})
    with pytest.raises(TrainerError, match="wings are unknown"):
        TrainConfig.from_dict({**d, "model": {**PAPER.as_dict(), "wings": 2}})
    full = TrainConfig(store="s.zarr", model=SPELT_OUT["R5-resp-d0"]).as_dict()
    assert TrainConfig.from_dict(full).model == SPELT_OUT["R5-resp-d0"]
