"""Named configurations of HeartUnloadNet (paper, multitoken, ablations A1–A5, baselines C0–C6, PCA)
and of a training run, as frozen dataclasses that round-trip through plain dicts (checkpoints, JSON)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace


class TrainerError(ValueError):
    """Bad input to training / evaluation / network unloading; the message is one line."""


class TrainingDiverged(TrainerError):
    """The training loss (or validation loss) turned non-finite: every rank stops at the same epoch."""


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
            trainer.sparse_gat; the default) | pyg (torch_geometric's GATConv). Same mathematics and
            parameter names: a checkpoint loads with either
    node_features: the encoder's node input — xyz (normalised coordinates: the paper) | wall
            (xyz plus the wall coordinates ζ, base 0 … apex 1, and τ, endocardium 0 … epicardium 1,
            trainer.data.wall_coordinates: where a node sits in the wall, which three message-passing
            hops cannot tell from coordinates; they label material points, so the cycle's pass on the
            predicted unloaded mesh reuses the ED values) | wall-response (wall plus the mesh's
            linear response ũ [3]: its displacement under pressure from one linear FE solve,
            trainer.data.linear_response_feature — how the whole shape gives, which no few-hop
            message passing can compute; ~45 ms per 350-node mesh, once, on top of the network's time)
    output_scale: how the decoders' output becomes a displacement — global (× one scale fitted on
            the training displacements: the paper) | load (also × the case's expected displacement
            size exp(load_features(p̂) · a), a fitted on the labelled training cases, trainer.data
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
        choices = {"conv": ("gat", "gatv2", "gcn", "sage"), "pooling": ("mean", "max", "none"),
                   "tokens": ("single", "regional"), "fusion": ("attention", "concat", "broadcast"),
                   "decoder": ("mlp", "gat"), "kind": ("gnn", "pca"), "gat_kernel": ("sparse", "pyg"),
                   "cycle_grad": ("both", "unloading", "teacher"), "node_features": ("xyz", "wall", "wall-response"),
                   "output_scale": ("global", "load")}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise TrainerError(f"model {name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if self.hidden < 1 or self.heads < 1 or self.layers < 1:
            raise TrainerError("model hidden, heads and layers must be ≥ 1")
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
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


PAPER = ModelConfig()
NAMED_CONFIGS: dict[str, ModelConfig] = {
    "paper": PAPER,
    "multitoken": replace(PAPER, tokens="regional"),
    "A1": replace(PAPER, cycle=False),  # no cycle
    "A2": replace(PAPER, fusion="concat"),  # concatenation instead of attention fusion
    "A3": replace(PAPER, pooling="none"),  # no pooling / mesh context
    "A4": replace(PAPER, conv="gcn"),  # GCN instead of GAT
    "A5": replace(PAPER, fusion="broadcast"),  # parameters broadcast to the nodes
    "C0": replace(PAPER, conv="gatv2"),
    "C2": replace(PAPER, conv="sage"),
    "C5": replace(PAPER, decoder="gat"),
    "C6": replace(PAPER, pooling="max"),
    "pca": replace(PAPER, kind="pca", cycle=False),
    # ours: the reverse (unloaded→ED) decoder also learns from the labelled pairs, so the cycle term
    # on unlabelled cases checks the unloading against a trained forward map (matters at low SR)
    "R1": replace(PAPER, reverse_weight=1.0),
    # R1 with λ_cycle ramped up over the first 10 epochs (the cycle term starts once the decoders
    # have learnt something from the labelled pairs)
    "R2": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10),
    # R2 with the reconstruction pass as a fixed teacher for the cycle term (stop-gradient): the
    # cycle moves only the unloading prediction; the reverse decoder learns from labelled pairs only
    "R3": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10, cycle_grad="unloading"),
    # R3 with the cycle term weighted like the supervised one (λ_cycle = 1): with the teacher fixed,
    # a larger weight cannot be met by the two maps agreeing on a wrong unloading
    "R4": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10, cycle_grad="unloading", lambda_cycle=1.0),
    # R4 with a mean teacher: the reconstruction pass runs on the weight average (EMA, d = 0.99),
    # which is also the model validated and saved
    "R5": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=10, cycle_grad="teacher", lambda_cycle=1.0,
                  ema_decay=0.99),
    # A1 (no cycle) with the same weight average, the fair baseline for R5
    "A1ema": replace(PAPER, cycle=False, ema_decay=0.99),
    # A1ema with the wall coordinates (ζ, τ) as node input besides the coordinates
    "A1ema-wall": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall"),
    # A1ema-wall without dropout: a displacement regression wants every feature, and the weight
    # average already smooths the step-to-step noise
    "A1ema-wall-d0": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall", dropout=0.0),
    # A1ema-wall-d0 whose output is scaled by the case's expected displacement size (from P, C, θ)
    "A1ema-wall-d0-load": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall", dropout=0.0,
                                  output_scale="load"),
    # A1ema-wall-d0 with the mesh's linear FE response as node input too
    "A1ema-resp-d0": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall-response", dropout=0.0),
    # A1ema-resp-d0 whose output is scaled by the case's expected displacement size (from P, C, θ),
    # for loadings beyond the trained grid (a softer wall than any trained one)
    "A1ema-resp-d0-load": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall-response", dropout=0.0,
                                  output_scale="load"),
    # the GCN baseline (A4) given the same inputs and recipe as A1ema-resp-d0: the fair test of attention
    "A1ema-resp-d0-gcn": replace(PAPER, cycle=False, ema_decay=0.99, node_features="wall-response", dropout=0.0,
                                 conv="gcn"),
    # R5 (the mean-teacher cycle) with A1ema-resp-d0's inputs, for the low-SR comparison on large
    # stores: λ_cycle at half weight in the first epoch, full from the second (an SR 3 % epoch of the
    # 60-shape paper grid is ~1,900 steps; R5's 10-epoch ramp was ~400 steps on the 20-shape store)
    "R5-resp-d0": replace(PAPER, reverse_weight=1.0, cycle_rampup_epochs=2, cycle_grad="teacher",
                          lambda_cycle=1.0, ema_decay=0.99, node_features="wall-response", dropout=0.0),
}
CONFIG_HELP = ("paper | multitoken | A1 (no cycle) | A2 (concat fusion) | A3 (no pooling) | A4 (GCN) | "
               "A5 (params broadcast) | C0 (GATv2) | C2 (GraphSAGE) | C5 (GAT decoder) | C6 (max pool) | "
               "R1 (reverse decoder supervised too) | R2 (R1, cycle ramped up) | "
               "R3 (R2, cycle gradient to the unloading only) | R4 (R3, λ_cycle 1) | R5 (R4, mean teacher) | "
               "A1ema (A1, weight average) | A1ema-wall (A1ema, wall coordinates as node input) | "
               "A1ema-wall-d0 (A1ema-wall, no dropout) | "
               "A1ema-wall-d0-load (A1ema-wall-d0, output scaled by the loading's displacement size) | "
               "A1ema-resp-d0 (A1ema-wall-d0 plus the mesh's linear FE response as node input) | "
               "A1ema-resp-d0-load (A1ema-resp-d0, output scaled by the loading's displacement size) | "
               "A1ema-resp-d0-gcn (A1ema-resp-d0 with GCN layers) | R5-resp-d0 (R5 with A1ema-resp-d0's inputs) | pca")


def named_config(name: str) -> ModelConfig:
    key = {k.lower(): k for k in NAMED_CONFIGS}.get(str(name).lower())
    if key is None:
        raise TrainerError(f"unknown --config {name!r}; choose {', '.join(NAMED_CONFIGS)}")
    return NAMED_CONFIGS[key]


LR_SCHEDULES = ("plateau", "cosine")


@dataclass(frozen=True)
class TrainConfig:
    """A training run: data, split, optimisation. Lengths mm; lr per AdamW step."""

    store: str
    config_name: str = "paper"
    model: ModelConfig = PAPER
    split: str = "shape"
    sr: float = 1.0  # supervision ratio: fraction of training cases whose label is used
    train_fraction: float = 1.0  # fraction of the training shapes kept (learning curves; trainer.splits)
    labelled_share: float = 0.25  # SR < 1: share of each batch drawn from the labelled cases (trainer.sampling)
    rotate_deg: float = 0.0  # augmentation: training graphs turned about the long axis by ±deg (trainer.augment)
    scale_pct: float = 0.0  # augmentation: training graphs scaled about their base by 1 ± pct/100 (trainer.augment)
    seed: int = 0  # initialisation, shuffling, augmentation; and the data's subsets unless split_seed is set
    split_seed: int | None = None  # split, SR subset and training-shape subset (None: seed)
    label_seed: int | None = None  # SR subset only (None: the split seed): other labels, same test cases
    epochs: int = 500
    batch_size: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    patience: int = 50  # early stopping, epochs without a better validation loss
    lr_schedule: str = "plateau"  # plateau (ReduceLROnPlateau: the paper) | cosine (trainer.schedule)
    lr_patience: int = 10  # ReduceLROnPlateau
    lr_factor: float = 0.5
    bf16: bool = False  # autocast on CUDA only
    compile: bool = False  # torch.compile the training forward/backward (dynamic shapes; minutes to compile)
    checkpoint_every: int = 1
    num_threads: int = 0  # torch threads per process (0: leave as is)

    def __post_init__(self):
        if not 0 < self.sr <= 1:
            raise TrainerError(f"--sr must be in (0, 1], got {self.sr}")
        if not 0 < self.train_fraction <= 1:
            raise TrainerError(f"--train-fraction must be in (0, 1], got {self.train_fraction}")
        if self.epochs < 1:
            raise TrainerError(f"--epochs must be ≥ 1, got {self.epochs}")
        if self.batch_size < 1:
            raise TrainerError(f"--batch-size must be ≥ 1, got {self.batch_size}")
        if not 0 <= self.labelled_share < 1:
            raise TrainerError(f"--labelled-share must be in [0, 1), got {self.labelled_share}")
        if self.seed < 0:
            raise TrainerError(f"--seed must be ≥ 0, got {self.seed}")
        if self.split_seed is not None and self.split_seed < 0:
            raise TrainerError(f"--split-seed must be ≥ 0, got {self.split_seed}")
        if self.label_seed is not None and self.label_seed < 0:
            raise TrainerError(f"--label-seed must be ≥ 0, got {self.label_seed}")
        if self.label_seed is not None and self.sr >= 1:
            raise TrainerError("--label-seed draws the SR subset; it needs --sr below 1")
        if self.lr_schedule not in LR_SCHEDULES:
            raise TrainerError(f"--lr-schedule must be one of {', '.join(LR_SCHEDULES)}, got {self.lr_schedule!r}")
        if not 0 <= self.rotate_deg <= 180:
            raise TrainerError(f"--rotate-deg must be in [0, 180], got {self.rotate_deg}")
        if not 0 <= self.scale_pct <= 30:
            raise TrainerError(f"--scale-pct must be in [0, 30], got {self.scale_pct}")

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
        names = {f.name for f in fields(cls)}
        d = {k: v for k, v in d.items() if k in names}
        d["model"] = ModelConfig.from_dict(d.get("model", {}))
        return cls(**d)

    def identity(self) -> dict:
        """What must agree for a run directory to be resumed (the rest, e.g. epochs, may change)."""
        from .splits import parse_split  # (splits imports this module)

        model = {k: v for k, v in self.model.as_dict().items() if k != "gat_kernel"}  # same maths either way
        ident = {"model": model, "split": parse_split(self.split), "sr": self.sr, "seed": self.seed,
                 "split_seed": self.data_seed, "train_fraction": self.train_fraction, "rotate_deg": self.rotate_deg,
                 "scale_pct": self.scale_pct, "batch_size": self.batch_size, "lr_schedule": self.lr_schedule,
                 "labelled_share": self.labelled_share, "weight_decay": self.weight_decay}
        if self.labels_seed != self.data_seed:  # runs from before --label-seed keep their identity
            ident["label_seed"] = self.labels_seed
        return ident
