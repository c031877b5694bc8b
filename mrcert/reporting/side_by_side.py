"""Camera motion smoothing, pixel-wise smoothing and bound propagation side by side
(``experiment=side_by_side``, docs/method.md §8, §9).

Rows per finished pixel-wise certify run of the experiment's sweep (axis, interval ``[-a, a]``,
frames), all restricted to that run's test images: the fixed-n CERTIFY run of
``experiment=reproduce_quick`` on the same axis and architecture, by camera motion smoothing,
once with its own motion-augmented model and once with the pixel-wise run's pixel-noise model
(``model.trained_for``: both methods on one base classifier, as the PwS authors compared them);
then the pixel-wise run; then the certify runs of the deterministic methods on the same interval
and images (``method=bound_propagation`` and, on translations, ``method=enumeration`` under
``experiment=reproduce_quick``, with each of the two base classifiers), where they have finished.
Each row gives the certified accuracy at the motion radius ``a``
(pixel-wise smoothing certifies the whole interval or nothing; motion smoothing certifies
``|motion| < R``) with its exact (Clopper-Pearson) 95% interval over the images, the base
classifier's accuracy on the clean test images and, for a pixel-noise model, on noisy ones (its
train run's ``test_acc_clean`` and ``test_acc``), the camera poses projected and the base
classifier's forward passes per image, seconds per image on the machine the run ran on and, for
pixel-wise smoothing, the images it left uncertified by cause (the logged ``margin``). The figure draws motion
smoothing's certified accuracy against radius on those images and pixel-wise smoothing's
certified accuracy at each interval.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mrcert.core.axes import unit
from mrcert.reporting import certify_log
from mrcert.reporting.cells import compose_config
from mrcert.reporting.experiment_cells import ExperimentCells, sweep_combos

EXPERIMENT = "side_by_side"
MOTION_EXPERIMENT = "reproduce_quick"
"""Where the motion-augmented models' certify runs come from (the same views, axis and model)."""
KINDS = MOTION_KIND, PIXEL_KIND, BOUND_KIND = ("smoothed over motions", "smoothed over pixels", "deterministic")
"""What each row's method certifies, in the page's order: camera motion smoothing, pixel-wise
smoothing, bound propagation."""


def _costs(log: pd.DataFrame, n: int) -> dict[str, float]:
    """Per image: camera poses projected (the log's ``projected``; a log written before it was
    recorded projects each of its ``n0 + n`` samples once, one frame) and forward passes
    (every sample classified: :func:`certify_log.samples`; pixel-wise smoothing stops at the first
    frame that rules the interval out)."""
    passes = certify_log.samples(log, n)
    projected = log["projected"] if "projected" in log and log["projected"].notna().all() else passes
    return {
        "poses projected / image": float(projected.mean()),
        "forward passes / image": float(passes.mean()),
        "seconds / image": float(log["seconds"].mean()),
    }


def _base_accuracy(src: ExperimentCells, run_id: str | None, noisy: bool) -> dict[str, float]:
    """The base classifier's test accuracy from its train run, on the clean test images and, for
    a pixel-noise model (``noisy``), on the noisy ones it was selected on (its ``test_acc``)."""
    metrics = (src.index.metrics(run_id) if run_id else None) or {}
    as_seen = metrics.get("test_acc", np.nan)
    if not noisy:
        return {"base clean accuracy": as_seen, "base noisy accuracy": np.nan}
    return {"base clean accuracy": metrics.get("test_acc_clean", np.nan), "base noisy accuracy": as_seen}


def _machine(src: ExperimentCells, run_id: str) -> str:
    """The machine a run ran on (its ``mrcert.machine`` tag): seconds per image are its pace there."""
    return (src.index.run_tags(run_id) or {}).get("mrcert.machine", "unknown")


def _why_not(log: pd.DataFrame) -> dict[str, float]:
    """Pixel-wise smoothing's images left uncertified, by cause, from the log's ``margin`` (the
    smallest over pieces of the better end frame's radius less the piece's bound): the bound
    (margin below 0: some piece's images may lie outside both its frames' certified balls) or
    the frames' classes (margin at least 0: they disagree, or one abstains)."""
    missed = log[log["radius"] <= 0]
    return {
        "left by the bound": float((missed["margin"] < 0).sum()),
        "left by the classes": float((missed["margin"] >= 0).sum()),
    }


def _certified(log: pd.DataFrame, radius: float) -> dict[str, float]:
    """Certified accuracy at ``radius`` over the log's images, with its exact 95% interval."""
    low, high = certify_log.certified_interval(log, radius)
    return {"certified accuracy": certify_log.certified_accuracy(log, radius), "low": low, "high": high}


DETERMINISTIC = (
    (("method=bound_propagation",), lambda c: f"bound propagation ({c.method.relaxation})", None),
    (("method=enumeration",), lambda c: "image enumeration (exact)", ("tx", "ty", "tz")),
)
"""The deterministic methods beside the smoothing methods: the overrides that pick each one's
certify runs, its label on the page, and the axes it certifies (None: every axis)."""


def _deterministic(log: pd.DataFrame) -> dict[str, float]:
    """Per image: camera poses projected, forward passes (poses classified; for image enumeration
    the images it classified, most of them incrementally) and seconds."""
    passes = log["forward_passes"] if "forward_passes" in log else log["classified"]  # enumeration: images
    return {
        "poses projected / image": float(log["projected"].mean()),
        "forward passes / image": float(passes.mean()),
        "seconds / image": float(log["seconds"].mean()),
        "left by the bound": float((log["outcome"] == "unknown").sum()),
        "left by the classes": float((log["outcome"] == "falsified").sum()),
    }


def _beside(src: ExperimentCells, overrides, images: set, fixed: dict, noisy: bool, label, costs) -> list[dict]:
    """The row (none if it has not run) of the finished certify run of ``overrides``, on the
    pixel-wise run's ``images``: ``fixed`` (the interval's columns, the kind, the base model),
    then ``label(cfg)`` as the method, its certified accuracy at the interval's half-width, the
    base classifier's accuracy (``noisy``: a pixel-noise model) and ``costs(log, cfg)``."""
    cell = src.index.cell(overrides)
    whole = src.index.log(cell)
    if whole is None:
        return []
    same = whole[whole["idx"].isin(images)]
    row = {
        "method": label(cell.cfg),
        "frames": np.nan,
        **_certified(same, fixed["half_width"]),
        **_base_accuracy(src, cell.train_run, noisy),
        **costs(same, cell.cfg),
        "machine": _machine(src, cell.run_ids[0]),
        "run_id": cell.run_ids[0],
        "train_run": cell.train_run,
        "log": same,
    }
    return [fixed | row]


def runs(src: ExperimentCells, experiment: str = EXPERIMENT, deterministic: tuple = DETERMINISTIC) -> pd.DataFrame:
    """Per finished pixel-wise run of the experiment, on its images: motion smoothing on the
    motion-augmented model and on the pixel-noise model (each where its run has finished), then
    pixel-wise smoothing; empty when no pixel-wise run has finished."""
    rows = []
    head = (f"profile={src.profile}", "task=certify")
    of_motion = tuple(o for o in src.overrides if not o.startswith("method."))  # method.*: pixel-wise's own
    motion_method = compose_config(["task=certify"]).method.name  # the default: camera motion smoothing
    for combo in sweep_combos(experiment):
        pixelwise = src.index.cell((f"experiment={experiment}", *head, *src.overrides, *combo))
        log = src.index.log(pixelwise)
        if log is None:
            continue
        cfg = pixelwise.cfg
        axis, half_width, frames = (
            str(cfg.motion.axis),
            float(cfg.method.certify.half_width),
            int(cfg.method.certify.frames),
        )
        images = set(log["idx"])
        common = {
            "axis": axis,
            "interval": f"+-{half_width:g} {unit(axis)}",
            "half_width": half_width,
            "model": str(cfg.model.arch),
            "images": len(images),
            "skip": int(cfg.task.skip),
        }
        noise = f"pixel-noise model (sigma {float(cfg.method.sigma):g})"
        own = (
            ("motion-augmented model", (), False),
            (noise, (f"model.trained_for={{name:pixelwise,sigma:{cfg.method.sigma}}}",), True),
        )
        where = (
            f"experiment={MOTION_EXPERIMENT}",
            *head,
            *of_motion,
            f"motion={axis}",
            f"model.variant={cfg.model.variant}",
        )
        for trained, extra, noisy in own:
            rows += _beside(
                src, (*where, *extra), images, common | {"kind": MOTION_KIND, "base model": trained}, noisy,
                lambda c: f"motion smoothing (sigma {float(c.motion.sigma):g} {unit(str(c.motion.axis))})",
                lambda same, c: _costs(same, int(c.task.n)),
            )  # fmt: skip
        rows.append(
            common
            | {
                "kind": PIXEL_KIND,
                "method": f"pixel-wise smoothing (sigma {float(cfg.method.sigma):g})",
                "base model": noise,
                "frames": frames,
                **_certified(log, half_width),
                **_base_accuracy(src, pixelwise.train_run, True),
                **_costs(log, int(cfg.task.n)),
                **_why_not(log),
                "machine": _machine(src, pixelwise.run_ids[0]),
                "run_id": pixelwise.run_ids[0],
                "train_run": pixelwise.train_run,
                "log": log,
            }
        )
        for method, label, axes in deterministic:  # each deterministic method on each base classifier
            if axes is not None and axis not in axes:
                continue
            for trained, extra, noisy in own:
                chosen = extra or (f"model.trained_for={{name:{motion_method}}}",)
                overrides = (f"task.skip={int(cfg.task.skip)}", *method, f"method.half_width={half_width}", *chosen)
                rows += _beside(
                    src, (*where, *overrides), images, common | {"kind": BOUND_KIND, "base model": trained}, noisy,
                    label, lambda same, c: _deterministic(same),
                )  # fmt: skip
    return pd.DataFrame(rows)


def shown_once(df: pd.DataFrame) -> pd.DataFrame:
    """Each run once per interval (a run beside the pixel-wise runs of both pixel sigmas appears
    under each), by axis, method, base model and interval."""
    order = {kind: k for k, kind in enumerate(KINDS)}
    return df.drop_duplicates(["interval", "run_id"]).sort_values(
        ["axis", "kind", "base model", "half_width"], key=lambda c: c.map(order) if c.name == "kind" else c
    )


def table(df: pd.DataFrame) -> pd.DataFrame:
    """The page's comparison: one row per axis, method and base model (with the base model's
    accuracy), one column per half-width ``a`` of the interval: the certified accuracy at ``a``
    with its exact 95% interval, empty where that run has not finished."""
    df = shown_once(df)
    keys = ["axis", "method", "base model"]
    widths = sorted(df["half_width"].unique())
    rows = []
    for (axis, method, model), group in df.groupby(keys, sort=False):
        first = group.iloc[0]
        row = {
            "axis": f"{axis} ({unit(axis)})",
            "method": method,
            "base model": model,
            "base clean accuracy": first["base clean accuracy"],
            "base noisy accuracy": first["base noisy accuracy"],
        }
        by_width = {float(r["half_width"]): r for _, r in group.iterrows()}
        for a in widths:
            r = by_width.get(float(a))
            row[f"+-{a:g}"] = "" if r is None else f"{r['certified accuracy']:.3f} ({r['low']:.2f}-{r['high']:.2f})"
        rows.append(row)
    out = pd.DataFrame(rows)
    for column in ("base clean accuracy", "base noisy accuracy"):
        out[column] = out[column].map(lambda v: "-" if pd.isna(v) else f"{v:.3f}")
    return out


def costs(df: pd.DataFrame) -> pd.DataFrame:
    """The runs behind :func:`table`, each once: what it cost per image and, for the methods that
    certify an interval, the images it left uncertified by cause. A motion smoothing run certifies
    a radius per image, so it serves every interval (``every a``). The machine column is there
    when the runs ran on more than one machine."""
    df = shown_once(df).drop_duplicates("run_id")
    out = df[
        [
            "axis",
            "interval",
            "method",
            "base model",
            "frames",
            "images",
            "left by the bound",
            "left by the classes",
            "poses projected / image",
            "forward passes / image",
            "seconds / image",
            "machine",
        ]
    ].copy()
    out.loc[df["kind"] == MOTION_KIND, "interval"] = "every a"
    for column in ("frames", "left by the bound", "left by the classes"):
        out[column] = out[column].map(lambda f: "-" if pd.isna(f) else str(int(f)))
    for column in ("poses projected / image", "forward passes / image"):
        out[column] = out[column].map(lambda v: f"{v:,.0f}")
    out["seconds / image"] = out["seconds / image"].map(lambda v: f"{v:.1f}")
    return out if out["machine"].nunique() > 1 else out.drop(columns="machine")


def figure(df: pd.DataFrame):
    """Per axis: motion smoothing's certified accuracy against radius (step curves, on the
    pixel-wise runs' images), and pixel-wise smoothing's (circles) and bound propagation's
    (hollow squares) at each interval; one colour per base model, the legends under the plots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = list(dict.fromkeys(df["axis"]))
    colours = {m: f"C{i}" for i, m in enumerate(dict.fromkeys(df["base model"]))}
    fig, grid = plt.subplots(1, len(axes), figsize=(max(7, 5.5 * len(axes)), 6.2), squeeze=False)
    for ax, axis in zip(grid.ravel(), axes, strict=True):
        rows = df[df["axis"] == axis]
        smallest = float(rows["half_width"].min())
        for _, row in rows[rows["kind"] == MOTION_KIND].drop_duplicates("base model").iterrows():
            radii, acc = certify_log.curve(row["log"])
            radii = np.maximum(radii, smallest / 10)  # log scale: radius 0 drawn at the left edge
            label = f"{row['method']}, {row['base model']}"
            x, y = np.append(radii, radii[-1] * 1.05), np.append(acc, 0.0)
            ax.step(x, y, where="pre", label=label, color=colours[row["base model"]])
        for (method, model), group in rows[rows["kind"] != MOTION_KIND].groupby(["method", "base model"]):
            frames = group["frames"].dropna().unique()
            label = f"{method}, {model}, whole interval" + (f", {int(frames[0])} frames" if len(frames) == 1 else "")
            if group["frames"].notna().all():  # pixel-wise smoothing
                style = {"marker": "o", "markersize": 6}
            else:  # the deterministic methods: hollow, so that a circle on the same point shows through
                marker, size = ("D", 14) if method.startswith("image enumeration") else ("s", 11)
                style = {"marker": marker, "markersize": size, "fillstyle": "none", "markeredgewidth": 1.5}
            ax.plot(
                group["half_width"],
                group["certified accuracy"],
                linestyle="none",
                color=colours[model],
                label=label,
                **style,
            )
            if len(frames) > 1:  # the frames differ between intervals: each point says its own
                for _, row in group[group["frames"].notna()].iterrows():
                    where = (row["half_width"], row["certified accuracy"])
                    ax.annotate(f"{int(row['frames'])} frames", where, fontsize=7)
        ax.set(
            xscale="log",
            xlabel=f"radius / half-width of the interval ({unit(axis)})",
            ylabel="certified accuracy",
            ylim=(-0.02, 1.02),
            title=f"{axis}, {rows['images'].iloc[0]} test images",
        )
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False)
    fig.suptitle("Motion smoothing, pixel-wise smoothing and bound propagation, same test views")
    fig.tight_layout()
    return fig
