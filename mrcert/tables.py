"""The paper's tables and figure, built from finished MLflow runs.

Runs are gathered with ``mlflow.search_runs`` into pandas and looked up by their tags (task,
dataset, profile, architecture, variant, axis; attack K). A cell with no run is empty (NaN,
written as an empty string), never zero. With ``show_paper`` a cell reads ``ours (paper)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from mrcert import certify_log, paper_results
from mrcert.paper_results import ARCHS, AXES_ORDER, VARIANTS

ARCH_NAMES = {"resnet18": "ResNet-18", "resnet50": "ResNet-50", "small_cnn": "SmallCNN"}
AXIS_NAMES = {"tz": "Tz", "tx": "Tx", "ty": "Ty", "rz": "Rz", "rx": "Rx", "ry": "Ry"}


@dataclass
class Runs:
    """Finished runs of one experiment, filtered by dataset and profile."""

    df: pd.DataFrame

    @classmethod
    def gather(cls, experiment: str, dataset: str | None = None, profile: str | None = None) -> Runs:
        import mlflow

        exp = mlflow.MlflowClient().get_experiment_by_name(experiment)
        if exp is None:
            return cls(pd.DataFrame())
        df = mlflow.search_runs([exp.experiment_id], filter_string="attributes.status = 'FINISHED'")
        if len(df) and dataset:
            df = df[df.get("tags.mrcert.dataset") == dataset]
        if len(df) and profile and "tags.mrcert.profile" in df:
            # Imported logs carry the profile their metadata names.
            df = df[df["tags.mrcert.profile"].fillna(profile) == profile]
        return cls(df.sort_values("start_time", ascending=False) if len(df) else df)

    def find(
        self,
        tasks: tuple[str, ...],
        arch: str | None = None,
        variant: str | None = None,
        axis: str | None = None,
        k: int | None = None,
        sigma: float | None = None,
    ) -> pd.Series | None:
        """The latest finished run matching every given key."""
        df = self.df
        if not len(df):
            return None
        mask = df["tags.mrcert.task"].isin(tasks)
        for col, value in (("tags.mrcert.model", arch), ("tags.mrcert.variant", variant), ("tags.mrcert.axis", axis)):
            if value is not None:
                mask &= df.get(col) == value
        if k is not None:
            mask &= pd.to_numeric(df.get("metrics.k"), errors="coerce") == k
        if sigma is not None:
            mask &= np.isclose(pd.to_numeric(df.get("params.motion.sigma"), errors="coerce"), sigma)
        hits = df[mask]
        return None if hits.empty else hits.iloc[0]

    def metric(self, name: str, tasks: tuple[str, ...], **keys) -> float:
        run = self.find(tasks, **keys)
        if run is None:
            return float("nan")
        if _is_shard(run):  # one shard's metrics describe its share only: use the merged log
            log = self.log_of(run)
            radius, step = float(run["params.motion.radius"]), float(run["params.motion.radius_step"])
            return certify_log.metrics(log, radius, step, radius)[0].get(name, float("nan"))
        value = run.get(f"metrics.{name}")
        return float(value) if value is not None and not pd.isna(value) else float("nan")

    def log_of(self, run: pd.Series) -> pd.DataFrame | None:
        """A certify run's log; for a shard, the merged logs of the latest run of every shard."""
        if not _is_shard(run):
            return _certify_log(run)
        group = self.df[self.df.get("tags.mrcert.shard_group") == run["tags.mrcert.shard_group"]]
        latest = group.drop_duplicates("params.task.shard")  # df is sorted newest first
        logs = [_certify_log(r) for _, r in latest.iterrows()]
        return None if any(log is None for log in logs) else certify_log.concat_logs(logs)


CERTIFY_TASKS = ("certify", "import")


def model_label(arch: str, variant: str, smoothed: bool = True) -> str:
    return f"{'Smoothed ' if smoothed else ''}{variant.capitalize()} {ARCH_NAMES.get(arch, arch)}"


# The paper's values of each measure (who, quantity, K); benign accuracy has no K.
PAPER = {
    ("base", "benign", None): paper_results.BASE_BENIGN,
    ("smoothed", "benign", None): paper_results.SMOOTHED_BENIGN,
    ("base", "perturbed", 100): paper_results.BASE_PERTURBED_100,
    ("smoothed", "perturbed", 100): paper_results.SMOOTHED_PERTURBED_100,
    ("smoothed", "perturbed", 5): paper_results.SMOOTHED_PERTURBED_5,
}


def measure(runs: Runs, who: str, quantity: str, k: int | None, **keys) -> float:
    """Accuracy of the ``base`` or ``smoothed`` model: ``benign``, or ``perturbed`` by K motions.

    Benign: the base model's from attack runs (of K perturbations when K is given), the
    smoothed model's from smooth runs; perturbed: from attack runs with K perturbations.
    """
    if quantity == "benign" and who == "smoothed":
        return runs.metric("smoothed_benign_accuracy", ("smooth",), **keys)
    name = "base_benign_accuracy" if quantity == "benign" else f"{who}_robust_accuracy"
    return runs.metric(name, ("attack",), k=k, **keys)


def paper_value(who: str, quantity: str, k: int | None, axis: str, arch: str, variant: str) -> float | None:
    table = PAPER.get((who, quantity, None if quantity == "benign" else k), {})
    return table.get((axis, arch, variant))


def certified_table(runs: Runs, archs=ARCHS, axes=AXES_ORDER, show_paper: bool = False) -> pd.DataFrame:
    """Table 3: benign, 5-perturbed and certified accuracy of the four smoothed models."""
    rows = {}
    for ax in axes:
        for a in archs:
            for v in VARIANTS:
                keys = {"arch": a, "variant": v, "axis": ax}
                rows[(AXIS_NAMES[ax], model_label(a, v))] = {
                    "Benign Acc": _cell(
                        measure(runs, "smoothed", "benign", None, **keys),
                        paper_value("smoothed", "benign", None, ax, a, v),
                        show_paper,
                    ),
                    "5-pert Emp. Acc": _cell(
                        measure(runs, "smoothed", "perturbed", 5, **keys),
                        paper_value("smoothed", "perturbed", 5, ax, a, v),
                        show_paper,
                    ),
                    "Certified Acc": _cell(
                        runs.metric("certified_accuracy", CERTIFY_TASKS, **keys),
                        paper_results.CERTIFIED.get((ax, a, v)),
                        show_paper,
                    ),
                }
    return _frame(rows, ["Axis", "Model"])


def base_vs_smoothed_table(
    runs: Runs, variant: str, archs=ARCHS, axes=AXES_ORDER, k: int = 100, show_paper: bool = False
) -> pd.DataFrame:
    """Table 1 (augmented) / its appendix twin (vanilla): benign and K-perturbed, base vs smoothed."""
    rows = {}
    for ax in axes:
        for quantity, label, kk in (
            ("benign", "Benign Accuracy", None),
            ("perturbed", f"{k}-perturbed Emp. Robust Acc.", k),
        ):
            rows[(AXIS_NAMES[ax], label)] = {
                f"{ARCH_NAMES.get(a, a)} {who.capitalize()}": _cell(
                    measure(runs, who, quantity, kk, arch=a, variant=variant, axis=ax),
                    paper_value(who, quantity, kk, ax, a, variant),
                    show_paper,
                )
                for a in archs
                for who in ("base", "smoothed")
            }
    return _frame(rows, ["Axis", "Metric"])


def perturbed_5_vs_100_table(runs: Runs, archs=ARCHS, axes=AXES_ORDER, show_paper: bool = False) -> pd.DataFrame:
    """Appendix: smoothed 5- vs 100-perturbed empirical robust accuracy."""
    rows = {}
    for ax in axes:
        for k in (5, 100):
            rows[(AXIS_NAMES[ax], f"{k}-perturbed")] = {
                f"{ARCH_NAMES.get(a, a)} {v.capitalize()}": _cell(
                    measure(runs, "smoothed", "perturbed", k, arch=a, variant=v, axis=ax),
                    paper_value("smoothed", "perturbed", k, ax, a, v),
                    show_paper,
                )
                for a in archs
                for v in VARIANTS
            }
    return _frame(rows, ["Axis", "Metric"])


def tabletop_table(
    runs: Runs, arch: str = "resnet18", variant: str = "vanilla", k: int = 10, show_paper: bool = False
) -> pd.DataFrame:
    """The real-robot table: benign and 10-perturbed accuracy, base vs smoothed, six axes.

    The paper reports one benign accuracy for both; ours is the mean over the six axes' runs."""
    axes = ("tx", "ty", "tz", "rx", "ry", "rz")
    data = {}
    for idx, who in enumerate(("base", "smoothed")):
        benign = [measure(runs, who, "benign", k, arch=arch, variant=variant, axis=ax) for ax in axes]
        ok = [b for b in benign if not np.isnan(b)]
        row = {
            "Benign Accuracy": _cell(
                float(np.mean(ok)) if ok else float("nan"), paper_results.TABLETOP_BENIGN, show_paper
            )
        }
        for ax in axes:
            row[AXIS_NAMES[ax]] = _cell(
                measure(runs, who, "perturbed", k, arch=arch, variant=variant, axis=ax),
                paper_results.TABLETOP_PERTURBED_10[ax][idx],
                show_paper,
            )
        data[who.capitalize()] = row
    df = pd.DataFrame.from_dict(data, orient="index")
    df.index.name = "Model"
    return df


def sweep_table(runs: Runs, parent: str | None = None) -> pd.DataFrame:
    """Certified accuracy against sigma (rows) and radius (columns) for each axis.

    From the children of ``parent`` (a sweep's parent run id) when given, else from every
    finished certify run. Radii are each axis's grid ``k * radius_step``.
    """
    df = runs.df
    if not len(df):
        return pd.DataFrame()
    df = df[df["tags.mrcert.task"].isin(CERTIFY_TASKS)]
    if parent:
        df = df[df.get("tags.mlflow.parentRunId") == parent]
    rows = []
    for _, run in df.iterrows():
        log = runs.log_of(run)
        if log is None:
            continue
        step = float(run.get("params.motion.radius_step", run.get("params.task.radius_step", "nan")))
        sigma = float(run.get("params.motion.sigma", run.get("params.task.sigma", "nan")))
        grid = certify_log.radius_grid(step, 4 * sigma)
        for r in grid[:: max(1, len(grid) // 8)]:
            rows.append(
                {
                    "Axis": run["tags.mrcert.axis"],
                    "sigma": sigma,
                    "radius": float(r),
                    "Certified Acc": certify_log.certified_accuracy(log, float(r)),
                    "start": run["start_time"],
                }
            )
    if not rows:
        return pd.DataFrame()
    long = pd.DataFrame(rows).sort_values("start", ascending=False).drop_duplicates(["Axis", "sigma", "radius"])
    wide = long.pivot_table(index=["Axis", "sigma"], columns="radius", values="Certified Acc")
    wide.columns = [f"r={c:.4g}" for c in wide.columns]
    return wide


def curves(runs: Runs, archs=ARCHS, axes=AXES_ORDER) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Per axis, per model: the exact step function (radii, certified accuracy) of its certify log."""
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for ax in axes:
        for a in archs:
            for v in VARIANTS:
                run = runs.find(CERTIFY_TASKS, arch=a, variant=v, axis=ax)
                log = None if run is None else runs.log_of(run)
                if log is not None:
                    out.setdefault(ax, {})[model_label(a, v)] = certify_log.curve(log)
    return out


def plot_curves(data: dict, path_stem: Path) -> list[Path]:
    """One panel per axis, one step curve per model; PNG and PDF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = [a for a in AXES_ORDER if a in data] or list(data)
    fig, panels = plt.subplots(2, 3, figsize=(12, 6.5), squeeze=False)
    for i, ax_name in enumerate(AXES_ORDER):
        panel = panels[i // 3][i % 3]
        panel.set(
            title=AXIS_NAMES[ax_name],
            xlabel="radius (m)" if ax_name.startswith("t") else "radius (rad)",
            ylabel="certified accuracy",
            ylim=(0, 1.02),
        )
        panel.grid(alpha=0.3)
        for label, (radii, acc) in data.get(ax_name, {}).items():
            end = radii[-1] * 1.05 + 1e-12
            panel.step(np.append(radii, end), np.append(acc, 0.0), where="pre", label=label, lw=1.6)
        if ax_name in data:
            panel.legend(fontsize=7)
    fig.suptitle("Certified accuracy against radius" + ("" if axes else " (no certify runs)"))
    fig.tight_layout()
    paths = [path_stem.with_suffix(".png"), path_stem.with_suffix(".pdf")]
    for p in paths:
        fig.savefig(p, dpi=130)
    plt.close(fig)
    return paths


def write(df: pd.DataFrame, stem: Path, caption: str) -> list[Path]:
    """Markdown, LaTeX and CSV of a table; empty cells stay empty."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    flat = df.reset_index()
    text = flat.map(format_cell) if hasattr(flat, "map") else flat.applymap(format_cell)
    md = stem.with_suffix(".md")
    md.write_text(f"**{caption}**\n\n" + markdown(text) + "\n")
    tex = stem.with_suffix(".tex")
    tex.write_text(_latex(text, caption))
    csv = stem.with_suffix(".csv")
    flat.to_csv(csv, index=False, na_rep="")
    return [md, tex, csv]


def format_cell(v) -> str:
    if isinstance(v, float):
        return "" if np.isnan(v) else f"{v:.3f}"
    return "" if v is None else str(v)


def markdown(text: pd.DataFrame) -> str:
    header = "| " + " | ".join(map(str, text.columns)) + " |"
    rule = "|" + "|".join("---" for _ in text.columns) + "|"
    body = ["| " + " | ".join(row) + " |" for row in text.astype(str).itertuples(index=False, name=None)]
    return "\n".join([header, rule, *body])


def _latex_escape(s: str) -> str:
    return (
        s.replace("\\", r"\textbackslash{}")
        .replace("&", r"\&")
        .replace("%", r"\%")
        .replace("_", r"\_")
        .replace("#", r"\#")
    )


def _latex(text: pd.DataFrame, caption: str) -> str:
    cols = "l" * len(text.columns)
    lines = [
        r"\begin{table}[ht]",
        r"\centering",
        rf"\begin{{tabular}}{{{cols}}}",
        r"\hline",
        " & ".join(_latex_escape(str(c)) for c in text.columns) + r" \\",
        r"\hline",
    ]
    lines += [
        " & ".join(_latex_escape(c) for c in row) + r" \\"
        for row in text.astype(str).itertuples(index=False, name=None)
    ]
    lines += [r"\hline", r"\end{tabular}", rf"\caption{{{_latex_escape(caption)}}}", r"\end{table}", ""]
    return "\n".join(lines)


def _cell(value: float, paper: float | None, show_paper: bool):
    if not show_paper:
        return value
    ours = "" if np.isnan(value) else f"{value:.3f}"
    return ours if paper is None else f"{ours} ({paper:.3f})"


def _frame(rows: dict[tuple[str, str], dict], index_names: list[str]) -> pd.DataFrame:
    """Rows keyed by (level 0, level 1), in insertion order, as a two-level indexed frame."""
    df = pd.DataFrame.from_dict(rows, orient="index")
    df.index = pd.MultiIndex.from_tuples(df.index, names=index_names)
    return df


def _is_shard(run: pd.Series) -> bool:
    return isinstance(run.get("tags.mrcert.shard_group"), str)


def _certify_log(run: pd.Series) -> pd.DataFrame | None:
    """The certify log of a run: from its output folder, else downloaded from its artifacts."""
    local = Path(str(run.get("tags.mrcert.output_dir", ""))) / "certify.tsv"
    if local.is_file():
        return certify_log.read_log(local)
    import mlflow

    for name in ("certify.tsv", Path(str(run.get("params.task.path", "x"))).name):
        try:
            return certify_log.read_log(
                Path(mlflow.artifacts.download_artifacts(run_id=run["run_id"], artifact_path=name))
            )
        except Exception:  # noqa: BLE001 - a run without that artifact: try the next name
            continue
    return None
