"""The learning curve: what it takes for a base classifier to generalise from the training
poses to the test views (``experiment=learning_curve`` for the small CNN under the paper's
separation rule, ``experiment=learning_curve_any`` for it under ``any``, for reference, and
``experiment=learning_curve_resnet18`` for the paper's ResNet-18; train runs only).

One row per finished train run of the experiments' sweeps (architecture, separation rule,
training poses per class, seed); the table gives the median over seeds of the selected model's
validation and test accuracy per architecture, the figure the test accuracy against training
poses per class and, per epoch and architecture, the validation and test accuracy each run
recorded (``val_acc``, ``epoch_test_acc``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mrcert.reporting.experiment_cells import ExperimentCells, sweep_combos
from mrcert.reporting.paper_tables import arch_name

EXPERIMENTS = ("learning_curve", "learning_curve_any", "learning_curve_resnet18")
"""The experiments whose train runs make the curve, the page's architecture (the small CNN) first."""


def runs(src: ExperimentCells, experiments: tuple[str, ...] = EXPERIMENTS) -> pd.DataFrame:
    """The experiments' finished train runs, one row each (empty when none has run), in the
    experiments' order; the source's overrides apply to every job except the keys the sweep sets."""
    rows = []
    for experiment, combo in ((e, c) for e in experiments for c in sweep_combos(e)):
        swept = {c.split("=", 1)[0] for c in combo}
        extra = tuple(o for o in src.overrides if o.split("=", 1)[0] not in swept)
        cell = src.index.cell((f"experiment={experiment}", f"profile={src.profile}", "task=train", *combo, *extra))
        if not cell.filled:
            continue
        cfg, run = cell.cfg, cell.runs[0]
        rows.append(
            {
                "separation rule": str(cfg.data.protocol.separation_rule),
                "training poses per class": int(cfg.data.protocol.train.per_class),
                "seed": int(cfg.seed),
                "model": str(cfg.model.arch),
                "epochs": int(cfg.train.epochs),
                "best epoch": run.get("metrics.best_epoch", np.nan),
                "validation accuracy": run.get("metrics.best_val_acc", np.nan),
                "test accuracy": run.get("metrics.test_acc", np.nan),
                "run_id": str(run["run_id"]),
            }
        )
    return pd.DataFrame(rows)


KEYS = ["separation rule", "model", "training poses per class"]
"""What a row of :func:`table` is: the runs with these in common (their seeds)."""


def table(df: pd.DataFrame) -> pd.DataFrame:
    """Median over seeds (and the range of the test accuracy) per rule, model and training poses;
    `every` first, the models in the order of the runs (the experiments' order)."""
    order = {"separation rule": {"every": 0, "any": 1}, "model": {m: k for k, m in enumerate(pd.unique(df["model"]))}}
    g = df.groupby(KEYS, sort=True)
    out = pd.DataFrame(
        {
            "seeds": g["seed"].count(),
            "validation accuracy (median)": g["validation accuracy"].median().round(3),
            "test accuracy (median)": g["test accuracy"].median().round(3),
            "test accuracy (min-max)": g["test accuracy"].agg(lambda s: f"{s.min():.3f}-{s.max():.3f}"),
        }
    ).reset_index()
    return out.sort_values(KEYS, key=lambda c: c.map(order[c.name]) if c.name in order else c)


def histories(df: pd.DataFrame, metrics=("val_acc", "epoch_test_acc")) -> dict[str, dict[str, np.ndarray]]:
    """Per run id, per metric: the value after each epoch (from MLflow's metric history)."""
    import mlflow

    client = mlflow.MlflowClient()
    out: dict[str, dict[str, np.ndarray]] = {}
    for run_id in df.get("run_id", []):
        out[run_id] = {}
        for m in metrics:
            hist = sorted(client.get_metric_history(run_id, m), key=lambda h: h.step)
            out[run_id][m] = np.array([h.value for h in hist])
    return out


def figure(df: pd.DataFrame, hist: dict[str, dict[str, np.ndarray]]):
    """Left: test accuracy against training poses per class (median over seeds, range as bars),
    one line per architecture and rule. Then one panel per architecture: validation and test
    accuracy after each epoch under `every`, one pair of lines per number of training poses
    (median over seeds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = list(pd.unique(df["model"]))
    fig, axes = plt.subplots(1, 1 + len(models), figsize=(5 * (1 + len(models)), 5.2), squeeze=False)
    left, per_epoch = axes[0][0], axes[0][1:]
    for k, ((model, rule), group) in enumerate(df.groupby(["model", "separation rule"], sort=False)):
        g = group.groupby("training poses per class")["test accuracy"]
        x, med = np.array(list(g.groups)), g.median().to_numpy()
        err = np.vstack([med - g.min().to_numpy(), g.max().to_numpy() - med])
        color, name = f"C{k}", f"{arch_name(model)}, `{rule}`"
        left.errorbar(x, med, yerr=err, marker="o", capsize=3, color=color, label=f"test, {name}")
        v = group.groupby("training poses per class")["validation accuracy"].median()
        left.plot(v.index, v.to_numpy(), ls=":", marker=".", color=color, label=f"validation, {name}")
    left.set(xlabel="training poses per class", ylabel="accuracy of best.pt", ylim=(0, 1.02), xscale="log")
    left.minorticks_off()
    left.set_xticks(sorted(df["training poses per class"].unique()))
    left.set_xticklabels([str(v) for v in sorted(df["training poses per class"].unique())])
    for ax, model in zip(per_epoch, models, strict=True):
        every = df[(df["separation rule"] == "every") & (df["model"] == model)]
        for i, (n, group) in enumerate(every.groupby("training poses per class")):
            color = f"C{i}"
            for metric, style, name in (("epoch_test_acc", "-", "test"), ("val_acc", ":", "validation")):
                curves = [hist[r][metric] for r in group["run_id"] if len(hist.get(r, {}).get(metric, []))]
                if not curves:
                    continue
                length = min(len(c) for c in curves)
                med = np.median(np.stack([c[:length] for c in curves]), axis=0)
                ax.plot(np.arange(1, length + 1), med, style, color=color, label=f"{n} poses, {name}")
        ax.set(
            xlabel="epoch",
            ylabel="accuracy (median over seeds)",
            ylim=(0, 1.02),
            title=f"{arch_name(model)}, separation `every`",
        )
    for ax in axes[0]:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.2))  # below: no line hidden
    fig.suptitle("Learning curves of the vanilla base classifiers on the synthetic MetaRoom")
    fig.tight_layout()
    return fig
