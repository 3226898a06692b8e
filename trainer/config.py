"""Named configurations of HeartUnloadNet (the paper's, its ablations and baselines, cycle variants, PCA)
and of a training run, as frozen dataclasses that round-trip through plain dicts (checkpoints, JSON)."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from trainer.errors import TrainerError
from trainer.data.splits import parse_split


def check_device(device: str) -> None:
    """TrainerError unless `device` is cpu, or cuda with a CUDA device present (torch loads only then)."""
    if device not in ("cpu", "cuda"):
        raise TrainerError(f"`device` must be cpu or cuda, got {device!r}")
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise TrainerError("`device` cuda: no CUDA device is available here")


# the values of ModelConfig's choice fields
MODEL_CHOICES = {"conv": ("gat", "gatv2", "gcn", "sage"), "pooling": ("mean", "max", "none"),
                 "tokens": ("single", "regional"), "fusion": ("attention", "concat", "broadcast"),
                 "decoder": ("mlp", "gat"), "kind": ("gnn", "pca"), "gat_kernel": ("sparse", "pyg"),
                 "cycle_grad": ("both", "unloading", "teacher"), "node_features": ("xyz", "wall", "wall-response"),
                 "output_scale": ("global", "load")}


@dataclass(frozen=True)
class ModelConfig:
    """Which parts make up the network. Every ablation and baseline is a value of this, not a copy
    of the model.

    conv: mesh-encoder layer — gat | gatv2 | gcn | sage
    pooling: mesh context from node features — mean | max | none (no mesh-context attention)
    tokens: global context — single (one pooled token, one parameter token: the paper's) |
            regional (pools over base/mid/apex × endo/epi plus the global pool; one token per
            parameter plus the joint one), so the attention weights can differ between tokens
    fusion: how the parameters reach the nodes — attention | concat | broadcast (raw parameters
            appended to the node input; no global encoder)
    decoder: mlp | gat
    cycle: run the shared encoder on the predicted unloaded mesh and decode back to ED
    cycle_grad: where the cycle term's gradient goes — both (the paper: the unloading path and the
            ED-reconstruction pass alike) | unloading (the reconstruction pass is a fixed teacher for
            that term: its weights get no cycle gradient, only the unloading prediction moves, so the
            two maps cannot co-adapt to agree on a wrong unloading; the reverse decoder then learns
            from the labelled pairs alone — use with reverse_weight > 0) | teacher (the same, but the
            reconstruction pass runs on the weight average below: a mean teacher, Tarvainen & Valpola
            2017, which changes slowly and averages out the student's step-to-step noise; needs
            ema_decay > 0)
    ema_decay: keep an exponential moving average of the weights, θ̄ ← d·θ̄ + (1 − d)·θ after every
            optimiser step (d warmed up as min(d, (1 + t)/(10 + t)) over the first steps t); the
            average is what validation sees and what the checkpoint saves as the best model.
            0 = off (the paper)
    gat_kernel: how GAT layers sum over neighbours — sparse (one sparse-matrix product per layer,
            trainer.network.sparse_gat; the default) | pyg (torch_geometric's GATConv). Same mathematics and
            parameter names: a checkpoint loads with either
    node_features: the encoder's node input — xyz (normalised coordinates: the paper) | wall
            (xyz plus the wall coordinates ζ, base 0 … apex 1, and τ, endocardium 0 … epicardium 1,
            trainer.data.features.wall_coordinates: where a node sits in the wall, which three message-passing
            hops cannot tell from coordinates; they label material points, so the cycle's pass on the
            predicted unloaded mesh reuses the ED values) | wall-response (wall plus the mesh's
            linear response ũ [3]: its displacement under pressure from one linear FE solve,
            trainer.data.features.linear_response_feature — how the whole shape gives, which no few-hop
            message passing can compute; ~45 ms per 350-node mesh, once, on top of the network's time)
    output_scale: how the decoders' output becomes a displacement — global (× one scale fitted on
            the training displacements: the paper) | load (also × the case's expected displacement
            size exp(load_features(p̂) · a), a fitted on the labelled training cases, trainer.data.store_cases
            fit_load_scale: the decoders predict a field of unit size for every loading, so a case at
            4 mmHg and C = 300 Pa is not fitted to the noise level of one at 14 mmHg and 50 Pa)
    kind: gnn | pca (the PCA displacement baseline; the other fields are ignored)
    """

    conv: str = "gat"
    hidden: int = 128  # per head
    heads: int = 4
    layers: int = 3
    dropout: float = 0.1
    pooling: str = "mean"
    tokens: str = "single"
    fusion: str = "attention"
    decoder: str = "mlp"
    cycle: bool = True
    lambda_cycle: float = 0.2
    reverse_weight: float = 0.0  # λ_rev: also supervise the reverse decoder on labelled pairs (0 = paper)
    cycle_rampup_epochs: int = 0  # λ_cycle grows linearly over the first epochs (0 = from the start, the paper)
    cycle_grad: str = "both"
    ema_decay: float = 0.0
    param_hidden: int = 128
    decoder_hidden: tuple = (256, 128)
    node_features: str = "xyz"
    output_scale: str = "global"
    kind: str = "gnn"
    gat_kernel: str = "sparse"
    pca_components: int = 16
    pca_ridge: float = 1e-2  # the PCA regression's ridge when the split has no validation cases (else chosen on them)

    def __post_init__(self):
        object.__setattr__(self, "decoder_hidden", tuple(int(v) for v in self.decoder_hidden))
        for name, allowed in MODEL_CHOICES.items():
            if getattr(self, name) not in allowed:
                raise TrainerError(f"model {name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if min(self.hidden, self.heads, self.layers, self.param_hidden, self.pca_components, *self.decoder_hidden) < 1:
            raise TrainerError("model hidden, heads, layers, param_hidden, pca_components and decoder_hidden must be ≥ 1")
        if not self.decoder_hidden:
            raise TrainerError("model decoder_hidden needs at least one layer width, e.g. 256,128")
        if not all(math.isfinite(v) for v in (self.lambda_cycle, self.reverse_weight, self.pca_ridge)) or self.pca_ridge < 0:
            raise TrainerError("model lambda_cycle, reverse_weight and pca_ridge must be finite, pca_ridge ≥ 0")
        if self.reverse_weight < 0 or self.lambda_cycle < 0 or self.cycle_rampup_epochs < 0:
            raise TrainerError("loss weights lambda_cycle, reverse_weight and cycle_rampup_epochs must be ≥ 0")
        if self.cycle_grad != "both" and self.cycle and self.reverse_weight <= 0:
            raise TrainerError(f"cycle_grad {self.cycle_grad!r} needs reverse_weight > 0 "
                               "(the reverse decoder would never learn)")
        if not 0 <= self.ema_decay < 1:
            raise TrainerError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        if self.cycle_grad == "teacher" and self.cycle and self.ema_decay <= 0:
            raise TrainerError("cycle_grad 'teacher' needs ema_decay > 0 (the teacher is the weight average)")
        if not 0 <= self.dropout < 1:
            raise TrainerError(f"dropout must be in [0, 1), got {self.dropout}")

    def cycle_weight(self, epoch: int) -> float:
        """λ_cycle in training epoch `epoch` (0-based): λ·min(1, (epoch + 1)/rampup)."""
        if self.cycle_rampup_epochs <= 0:
            return self.lambda_cycle
        return self.lambda_cycle * min(1.0, (epoch + 1) / self.cycle_rampup_epochs)

    @property
    def uses_attention_graph(self) -> bool:
        """Whether GAT layers run on the sparse kernel, which takes a batch's edges as an
        AttentionGraph (built once per batch, or assembled from each mesh's by a GraphTable)."""
        return self.kind == "gnn" and self.gat_kernel == "sparse" and "gat" in (self.conv, self.decoder)

    @property
    def uses_response(self) -> bool:
        """Whether the graphs must carry the linear response (node_features wall-response)."""
        return self.kind == "gnn" and self.node_features == "wall-response"

    @property
    def uses_wall(self) -> bool:
        """Whether the node input holds the wall coordinates (ζ, τ)."""
        return self.node_features in ("wall", "wall-response")

    @property
    def width(self) -> int:
        """Node feature width (heads concatenated): 128 × 4 = 512 for the paper."""
        return self.hidden * self.heads

    def as_dict(self) -> dict:
        d = asdict(self)
        d["decoder_hidden"] = list(self.decoder_hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if unknown:
            raise TrainerError(f"the network settings {', '.join(map(str, unknown))} are unknown to this heartctl "
                               f"(written by a newer one?)")
        return cls(**d)


PAPER = ModelConfig()
# The names `--config` offers: the seed paper's model, its ablations and baselines, our cycle variants
# and the PCA baseline. Any other network is one of these plus options (compose).
BASE_CONFIGS: dict[str, ModelConfig] = {
    "paper": PAPER,
    "multitoken": replace(PAPER, tokens="regional"),
    "no-cycle": replace(PAPER, cycle=False),
    "concat-fusion": replace(PAPER, fusion="concat"),  # concatenation instead of attention fusion
    "no-pooling": replace(PAPER, pooling="none"),  # no mesh-context attention
    "gcn": replace(PAPER, conv="gcn"),
    "broadcast-fusion": replace(PAPER, fusion="broadcast"),  # raw parameters appended to the node input
    "gatv2": replace(PAPER, conv="gatv2"),
    "sage": replace(PAPER, conv="sage"),
    "gat-decoder": replace(PAPER, decoder="gat"),
    "max-pooling": replace(PAPER, pooling="max"),
    # the reverse (unloaded→ED) decoder also learns from the labelled pairs, so the cycle term on
    # unlabelled cases checks the unloading against a trained forward map (matters at low SR)
    "reverse": replace(PAPER, reverse_weight=1.0),
    # reverse, with λ_cycle ramped up over the first 10 epochs (the cycle term starts once the decoders
    # have learnt something from the labelled pairs)
    "reverse-rampup": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10),
    # reverse-rampup with the reconstruction pass as a fixed teacher for the cycle term (stop-gradient):
    # the cycle moves only the unloading prediction; the reverse decoder learns from labelled pairs only
    "fixed-teacher": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10, cycle_grad="unloading"),
    # fixed-teacher with the cycle term weighted like the supervised one (λ_cycle = 1): with the teacher
    # fixed, a larger weight cannot be met by the two maps agreeing on a wrong unloading
    "fixed-teacher-full-cycle": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10, cycle_grad="unloading",
                                        lambda_cycle=1.0),
    # fixed-teacher-full-cycle with a mean teacher: the reconstruction pass runs on the weight average
    # (EMA, d = 0.99), which is also the model validated and saved
    "mean-teacher": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10, cycle_grad="teacher",
                            lambda_cycle=1.0, ema_decay=0.99),
    "pca": replace(PAPER, kind="pca", cycle=False),
}
# The coded names of the paper's ablation (A) and baseline (C) tables and of our cycle variants (R):
# `--config` accepts them, and the ablation tables print them beside the names.
CODES: dict[str, str] = {"A1": "no-cycle", "A2": "concat-fusion", "A3": "no-pooling", "A4": "gcn",
                         "A5": "broadcast-fusion", "C0": "gatv2", "C2": "sage", "C5": "gat-decoder",
                         "C6": "max-pooling", "R1": "reverse", "R2": "reverse-rampup", "R3": "fixed-teacher",
                         "R4": "fixed-teacher-full-cycle", "R5": "mean-teacher"}

# `heartctl train` options that set one network field each: option → field
OPTION_FIELDS = {"node-input": "node_features", "ema": "ema_decay", "dropout": "dropout",
                 "output-scale": "output_scale", "layer": "conv"}
NODE_INPUTS = {"xyz": "xyz", "wall": "wall", "response": "wall-response"}  # --node-input → node_features
_RESPONSE_D0 = {"ema_decay": 0.99, "node_features": "wall-response", "dropout": 0.0}


@dataclass(frozen=True)
class Preset:
    """A named network with the training options that go with it (TrainConfig fields)."""

    model: ModelConfig
    training: tuple = ()  # (TrainConfig field, value) pairs


# recommended: the lowest measured error (docs/training.md, "Which configuration to use")
PRESETS: dict[str, Preset] = {
    "recommended": Preset(replace(BASE_CONFIGS["no-cycle"], **_RESPONSE_D0),
                          (("scale_pct", 8.0), ("lr_schedule", "cosine"))),
}
# Compatibility: the coded names of the benchmark tables and run directories, each a base plus
# settings; accepted by --config and resolved when a checkpoint names one.
ALIASES: dict[str, tuple[str, dict]] = {
    **{code: (name, {}) for code, name in CODES.items()},
    "A1ema": ("no-cycle", {"ema_decay": 0.99}),
    "A1ema-wall": ("no-cycle", {"ema_decay": 0.99, "node_features": "wall"}),
    "A1ema-wall-d0": ("no-cycle", {"ema_decay": 0.99, "node_features": "wall", "dropout": 0.0}),
    "A1ema-wall-d0-load": ("no-cycle", {"ema_decay": 0.99, "node_features": "wall", "dropout": 0.0,
                                        "output_scale": "load"}),
    "A1ema-resp-d0": ("no-cycle", _RESPONSE_D0),
    "A1ema-resp-d0-load": ("no-cycle", {**_RESPONSE_D0, "output_scale": "load"}),
    "A1ema-resp-d0-gcn": ("no-cycle", {**_RESPONSE_D0, "conv": "gcn"}),
    "R5-resp-d0": ("mean-teacher", {"node_features": "wall-response", "dropout": 0.0, "cycle_rampup_epochs": 2}),
}
CONFIG_HELP = ("Base network: paper (default) | multitoken | no-cycle, concat-fusion, no-pooling, gcn, "
               "broadcast-fusion (the paper's ablations A1–A5) | gatv2, sage, gat-decoder, max-pooling (its "
               "baselines C0, C2, C5, C6) | reverse, reverse-rampup, fixed-teacher, fixed-teacher-full-cycle, "
               "mean-teacher (cycle variants R1–R5) | pca | recommended (no-cycle + node-input response, ema 0.99, "
               "dropout 0, with `scale_pct` 8 `lr_schedule` cosine). The codes are accepted too. Options below "
               "change it (docs/training.md: Configurations).")


def canonical_name(name: str) -> str:
    """The descriptive name of a coded base configuration (A1 → no-cycle); any other name as given."""
    key = str(name).strip()
    return next((v for k, v in CODES.items() if k.lower() == key.lower()), key)


def code_of(name: str) -> str:
    """The paper-table code of a base configuration's name (no-cycle → A1), or "" if it has none."""
    return next((k for k, v in CODES.items() if v == canonical_name(name)), "")


def _lookup(name) -> Preset | None:
    key = str(name).lower()
    for table in (BASE_CONFIGS, PRESETS, ALIASES):
        hit = next((v for k, v in table.items() if k.lower() == key), None)
        if isinstance(hit, ModelConfig):
            return Preset(hit)
        if isinstance(hit, tuple):
            return Preset(replace(BASE_CONFIGS[hit[0]], **hit[1]))
        if hit is not None:
            return hit
    return None


def preset(name: str) -> Preset:
    """The network and training options `--config NAME` starts from (case-insensitive)."""
    found = _lookup(name)
    if found is None:
        raise TrainerError(f"unknown configuration {name!r}; choose {', '.join([*BASE_CONFIGS, *PRESETS])}")
    return found


def named_config(name: str) -> ModelConfig:
    """The network of `--config NAME` (a preset's network without its training options)."""
    return preset(name).model


# every name --config accepts → its network
NAMED_CONFIGS: dict[str, ModelConfig] = {n: named_config(n) for n in (*BASE_CONFIGS, *PRESETS, *ALIASES)}
# training fields `--set` may change (the others have options of their own)
SET_TRAIN_KEYS = ("weight_decay", "lr_patience", "lr_factor")
_TRAIN_DEFAULTS = {"weight_decay": 1e-4, "lr_patience": 10, "lr_factor": 0.5}


def _convert(key: str, text: str, like):
    """`text` as a value of the type of `like` (a field's default); TrainerError if it does not read."""
    text = text.strip()
    try:
        if isinstance(like, bool):
            value = {"true": True, "yes": True, "on": True, "1": True,
                     "false": False, "no": False, "off": False, "0": False}[text.lower()]
        elif isinstance(like, int):
            value = int(text)
        elif isinstance(like, float):
            value = float(text)
            if not math.isfinite(value):
                raise ValueError
        elif isinstance(like, tuple):
            value = tuple(int(v) for v in text.split(","))
        else:
            value = text
    except (KeyError, ValueError):
        kind = {bool: "true or false", int: "an integer", float: "a finite number",
                tuple: "comma-separated integers"}[type(like)]
        raise TrainerError(f"`set` {key}={text}: {key} takes {kind}") from None
    return value


def parse_settings(items) -> tuple[dict, dict]:
    """`--set key=value` items → (network field changes, training field changes), each value read as
    its field's type; TrainerError (one line) for a malformed item or a key no field has. Hyphens in
    a key read as underscores."""
    defaults = {f.name: f.default for f in fields(ModelConfig)}
    model, training = {}, {}
    for item in items:
        key, sep, text = str(item).partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key:
            raise TrainerError(f"`set` takes key=value, e.g. `set` hidden=64; got {item!r}")
        if key in defaults:
            model[key] = _convert(key, text, defaults[key])
        elif key in SET_TRAIN_KEYS:
            training[key] = _convert(key, text, _TRAIN_DEFAULTS[key])
        else:
            raise TrainerError(f"unknown `set` key {key!r}; network keys: {', '.join(defaults)}; "
                               f"training keys: {', '.join(SET_TRAIN_KEYS)} (the others have options of their own)")
    return model, training


def compose(name: str = "paper", *, node_input: str | None = None, ema: float | None = None,
            dropout: float | None = None, output_scale: str | None = None, layer: str | None = None,
            settings=()) -> tuple[ModelConfig, dict]:
    """The network and training fields of `--config NAME` with options on top (None: not given):
    the preset's own, then the named options, then the `--set` items. Validated by the dataclasses:
    TrainerError (one line) for an unknown name, key or a bad value."""
    start = preset(name)
    changes = {}
    for option, value, allowed in (("node-input", node_input, tuple(NODE_INPUTS)),
                                   ("output-scale", output_scale, MODEL_CHOICES["output_scale"]),
                                   ("layer", layer, MODEL_CHOICES["conv"])):
        if value is not None and value not in allowed:
            raise TrainerError(f"--{option} must be one of {', '.join(allowed)}, got {value!r}")
    for option, value in (("node-input", NODE_INPUTS.get(node_input)), ("ema", ema), ("dropout", dropout),
                          ("output-scale", output_scale), ("layer", layer)):
        if value is not None:
            changes[OPTION_FIELDS[option]] = value
    model_sets, training_sets = parse_settings(settings)
    model = replace(start.model, **{**changes, **model_sets})
    return model, {**dict(start.training), **training_sets}


def _shown(field: str, value) -> str:
    if field == "node_features":
        return {v: k for k, v in NODE_INPUTS.items()}[value]
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return ",".join(map(str, value))
    return str(value)


def describe_model(model: ModelConfig) -> str:
    """The network in the terms of the train options: the nearest base configuration and what differs
    from it, e.g. "no-cycle + node-input response, ema 0.99, dropout 0" (options first, `--set` keys after)."""
    compared = ([f.name for f in fields(ModelConfig)] if model.kind == "gnn" else ["pca_components", "pca_ridge"])

    def differences(base: ModelConfig) -> list:
        return [k for k in compared if getattr(base, k) != getattr(model, k)]

    names = [n for n, m in BASE_CONFIGS.items() if m.kind == model.kind]
    base = min(names, key=lambda n: len(differences(BASE_CONFIGS[n])))  # the first on a tie
    options = {f: o for o, f in OPTION_FIELDS.items()}
    keys = sorted(differences(BASE_CONFIGS[base]), key=lambda k: list(options).index(k) if k in options else len(options))
    parts = [f"{options[k]} {_shown(k, getattr(model, k))}" if k in options else f"{k}={_shown(k, getattr(model, k))}"
             for k in keys]
    return base + (" + " + ", ".join(parts) if parts else "")


LR_SCHEDULES = ("plateau", "cosine")


@dataclass(frozen=True)
class TrainConfig:
    """A training run: data, split, optimisation. Lengths mm; lr per AdamW step."""

    store: str
    config_name: str = "paper"
    model: ModelConfig = PAPER
    split: str = "shape"
    sr: float = 1.0  # supervision ratio: fraction of training cases whose label is used
    train_fraction: float = 1.0  # fraction of the training shapes kept (learning curves; trainer.data.splits)
    labelled_share: float = 0.25  # SR < 1: share of each batch drawn from the labelled cases (trainer.data.sampling)
    rotate_deg: float = 0.0  # augmentation: training graphs turned about the long axis by ±deg (trainer.data.augment)
    scale_pct: float = 0.0  # augmentation: training graphs scaled about their base by 1 ± pct/100 (trainer.data.augment)
    seed: int = 0  # initialisation, shuffling, augmentation; and the data's subsets unless split_seed is set
    split_seed: int | None = None  # split, SR subset and training-shape subset (None: seed)
    label_seed: int | None = None  # SR subset only (None: the split seed): other labels, same test cases
    epochs: int = 500
    batch_size: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    patience: int = 50  # early stopping, epochs without a better validation loss
    lr_schedule: str = "plateau"  # plateau (ReduceLROnPlateau: the paper) | cosine (trainer.training.schedule)
    lr_patience: int = 10  # ReduceLROnPlateau
    lr_factor: float = 0.5
    bf16: bool = False  # autocast on CUDA only
    compile: bool = False  # torch.compile the training forward/backward (dynamic shapes; minutes to compile)
    checkpoint_every: int = 1
    num_threads: int = 0  # torch threads per process (0: leave as is)
    init_from: str | None = None  # fine-tuning: the parent checkpoint whose weights and normalisation the run starts from
    init_from_sha256: str | None = None  # the parent's tensors digest, recorded when the run starts (trainer.training.finetune)

    def __post_init__(self):
        if not 0 < self.sr <= 1:
            raise TrainerError(f"`sr` must be in (0, 1], got {self.sr}")
        if not 0 < self.train_fraction <= 1:
            raise TrainerError(f"`train_fraction` must be in (0, 1], got {self.train_fraction}")
        if self.epochs < 1:
            raise TrainerError(f"`epochs` must be ≥ 1, got {self.epochs}")
        if self.batch_size < 1:
            raise TrainerError(f"`batch_size` must be ≥ 1, got {self.batch_size}")
        if not 0 < self.lr < math.inf:
            raise TrainerError(f"`lr` must be a finite number > 0, got {self.lr}")
        if self.patience < 1:
            raise TrainerError(f"`patience` must be ≥ 1, got {self.patience}")
        if not 0 <= self.labelled_share < 1:
            raise TrainerError(f"`labelled_share` must be in [0, 1), got {self.labelled_share}")
        if self.seed < 0:
            raise TrainerError(f"`seed` must be ≥ 0, got {self.seed}")
        if self.split_seed is not None and self.split_seed < 0:
            raise TrainerError(f"`split_seed` must be ≥ 0, got {self.split_seed}")
        if self.label_seed is not None and self.label_seed < 0:
            raise TrainerError(f"`label_seed` must be ≥ 0, got {self.label_seed}")
        if self.label_seed is not None and self.sr >= 1:
            raise TrainerError("`label_seed` draws the SR subset; it needs `sr` below 1")
        if self.lr_schedule not in LR_SCHEDULES:
            raise TrainerError(f"`lr_schedule` must be one of {', '.join(LR_SCHEDULES)}, got {self.lr_schedule!r}")
        if not 0 <= self.rotate_deg <= 180:
            raise TrainerError(f"`rotate_deg` must be in [0, 180], got {self.rotate_deg}")
        if not 0 <= self.scale_pct <= 30:
            raise TrainerError(f"`scale_pct` must be in [0, 30], got {self.scale_pct}")
        if not (math.isfinite(self.weight_decay) and self.weight_decay >= 0):
            raise TrainerError(f"weight_decay must be a finite number ≥ 0, got {self.weight_decay}")
        if self.lr_patience < 0 or not 0 < self.lr_factor < 1:
            raise TrainerError(f"lr_patience must be ≥ 0 and lr_factor in (0, 1), got {self.lr_patience} and {self.lr_factor}")
        if self.init_from is not None and not str(self.init_from).strip():
            raise TrainerError("`init_from` takes a run directory or its checkpoint.pt")
        if self.init_from is not None and self.model.kind == "pca":
            raise TrainerError("`init_from` starts a network from trained weights; the PCA baseline is fitted in one step")
        if self.init_from_sha256 is not None and (self.init_from is None or len(self.init_from_sha256) != 64
                                                  or any(c not in "0123456789abcdef" for c in self.init_from_sha256)):
            raise TrainerError("init_from_sha256 must be the parent checkpoint's 64-digit hex digest, with init_from set")

    @property
    def data_seed(self) -> int:
        """The seed of the split, the SR subset and the training-shape subset: networks trained with
        one data seed and several seeds share their test cases (a seed ensemble)."""
        return self.seed if self.split_seed is None else self.split_seed

    @property
    def labels_seed(self) -> int:
        """The seed of the SR subset (which training cases keep their label): --label-seed, else the
        data seed. Runs with one split seed and several label seeds share their test cases but learn
        from different labelled pairs."""
        return self.data_seed if self.label_seed is None else self.label_seed

    def as_dict(self) -> dict:
        d = asdict(self)
        d["model"] = self.model.as_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """Read back as_dict's output. A dict without the network's settings (none are written so)
        resolves its config_name, old coded names included; TrainerError if that name is unknown."""
        names = {f.name for f in fields(cls)}
        d = {k: v for k, v in d.items() if k in names}
        if isinstance(d.get("model"), dict):
            d["model"] = ModelConfig.from_dict(d["model"])
        else:
            name = d.get("config_name", "paper")
            if _lookup(name) is None:
                raise TrainerError(f"configuration {name!r} lists no network settings and is not a name this heartctl "
                                   f"knows; train it again")
            d["model"] = named_config(name)
        return cls(**d)

    def identity(self) -> dict:
        """What must agree for a run directory to be resumed (the rest, e.g. epochs, may change)."""
        model = {k: v for k, v in self.model.as_dict().items() if k != "gat_kernel"}  # same maths either way
        ident = {"model": model, "split": parse_split(self.split), "sr": self.sr, "seed": self.seed,
                 "split_seed": self.data_seed, "train_fraction": self.train_fraction, "rotate_deg": self.rotate_deg,
                 "scale_pct": self.scale_pct, "batch_size": self.batch_size, "lr_schedule": self.lr_schedule,
                 "labelled_share": self.labelled_share, "weight_decay": self.weight_decay}
        if self.labels_seed != self.data_seed:  # runs from before --label-seed keep their identity
            ident["label_seed"] = self.labels_seed
        if self.init_from is not None:  # the parent's weights, wherever its file lies (runs without one keep their identity)
            ident["init_from_sha256"] = self.init_from_sha256
        return ident


# the training fields a configuration line shows when they differ from their defaults (what is learned
# and how; not epochs' budget, precision or threads)
_SHOWN_TRAINING = ("split", "sr", "labelled_share", "train_fraction", "rotate_deg", "scale_pct", "seed", "split_seed",
                   "label_seed", "batch_size", "lr", "lr_schedule", *SET_TRAIN_KEYS, "init_from")


def describe_run(cfg: TrainConfig) -> str:
    """A run's configuration on one line: its network (describe_model), then the training options that
    differ from their defaults, named after the preset it matches, e.g. "recommended = A1 + node-input
    response, ema 0.99, dropout 0; scale-pct 8, lr-schedule cosine"."""
    default = TrainConfig(store=cfg.store)
    shown = [f"{k}={_shown(k, getattr(cfg, k))}" if k in SET_TRAIN_KEYS else f"{k.replace('_', '-')} {_shown(k, getattr(cfg, k))}"
             for k in _SHOWN_TRAINING if getattr(cfg, k) != getattr(default, k)]
    text = describe_model(cfg.model) + ("; " + ", ".join(shown) if shown else "")
    named = next((n for n, p in PRESETS.items() if p.model == cfg.model
                  and all(getattr(cfg, k) == v for k, v in p.training)), None)
    return f"{named} = {text}" if named else text
