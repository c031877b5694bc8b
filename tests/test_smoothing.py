"""Motion smoothing: exact statistics, PREDICT, determinism across batches and shards, resume, import."""

from pathlib import Path
from statistics import NormalDist

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch
from statsmodels.stats.proportion import proportion_confint
from torch import nn

from mrcert.__main__ import run_task
from mrcert.core.methods.base import ABSTAIN
from mrcert.core.methods.camera_motion import CameraMotionSmoothing
from mrcert.core.sampling import SmoothedClassifier, image_generator
from mrcert.core.sequential import lower_confidence_bound
from mrcert.data.samples import TestSample
from mrcert.errors import MrcertError
from mrcert.infra.runtime import render_batch
from mrcert.reporting.certify_log import ResultLog, concat_logs, read_log
from tests.conftest import PAPER_K, TINY, TINY_CLASSES, compose_cfg, kill_when, run_cli

ROOT = Path(__file__).resolve().parent.parent
FAST_CERTIFY = ["task=certify", "task.n0=8", "task.n=40", "task.max=6", "task.batch_size=8"]
PER_RUN = ["time", "seconds", "check"]  # cells that differ between two runs of one result


def tiny_cfg(overrides, outputs):
    return compose_cfg([*TINY, *overrides], outputs)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A store with one finished tiny train run (the classifier the tasks look up)."""
    outputs = tmp_path_factory.mktemp("store")
    run_task(
        tiny_cfg(["task=train", "train.epochs=2", "train.lr=0.05", "train.batch_size=8"], outputs),
        outputs / "runs" / "train",
    )
    return outputs


class Constant(nn.Module):
    def __init__(self, cls: int, num_classes: int = 4):
        super().__init__()
        self.cls, self.num_classes = cls, num_classes

    def forward(self, x):
        out = torch.zeros(len(x), self.num_classes)
        out[:, self.cls] = 1.0
        return out


def tiny_sample() -> TestSample:
    pts = np.random.default_rng(0).uniform([-1, -1, 2], [1, 1, 3], (500, 3))
    colors = np.random.default_rng(1).uniform(0, 0.9, (500, 3)).astype(np.float32)
    return TestSample.build(pts, colors, PAPER_K, 90, 160, label=2)


def test_clopper_pearson_oracles():
    assert lower_confidence_bound(990, 1000, 0.001) == pytest.approx(0.9760361871553114, abs=1e-15)
    for count, n in ((990, 1000), (1, 100), (57, 100), (1000, 1000), (500, 1000)):
        expected = proportion_confint(count, n, alpha=0.02, method="beta")[0]
        assert lower_confidence_bound(count, n, 0.01) == pytest.approx(expected, abs=1e-12)
    assert lower_confidence_bound(0, 1000, 0.01) == 0.0  # no NaN for nA = 0
    assert lower_confidence_bound(1000, 1000, 0.01) == pytest.approx(0.01 ** (1 / 1000))  # < 1: finite radius


def test_constant_classifier_certifies_2_605_sigma():
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    smoothed = SmoothedClassifier(Constant(2), dist, 4)
    cert = smoothed.certify(tiny_sample().renderer(), 100, 1000, 0.01, image_generator(0, 0))
    assert (cert.prediction, cert.count_a) == (2, 1000)
    assert cert.radius == pytest.approx(0.1 * NormalDist().inv_cdf(0.01 ** (1 / 1000)), abs=1e-12)
    assert cert.radius / 0.1 == pytest.approx(2.605, abs=5e-4)


class NaNFor(Constant):
    """Class ``cls``, except NaN logits for the images whose first pixel is above ``threshold``."""

    def __init__(self, cls: int, threshold: float):
        super().__init__(cls)
        self.threshold = threshold

    def forward(self, x):
        out = super().forward(x)
        out[x[:, 0, 0, 0] > self.threshold] = float("nan")
        return out


def test_a_non_finite_logit_is_never_a_vote():
    """NaN logits argmax to class 0; they must count for no class: a model with NaN logits
    everywhere abstains, and one with them on some samples gets no votes from those."""
    dist = CameraMotionSmoothing(("tz",), (0.1,))
    render = tiny_sample().renderer()
    nan = SmoothedClassifier(NaNFor(2, threshold=-1.0), dist, 4)
    assert nan.sample_counts(render, 50, image_generator(0, 0)).tolist() == [0, 0, 0, 0]
    cert = nan.certify(render, 20, 100, 0.01, image_generator(0, 0))
    assert cert.prediction == ABSTAIN
    some = SmoothedClassifier(NaNFor(2, threshold=2.0), dist, 4)  # a pixel is never above 2: no NaN
    assert some.sample_counts(render, 50, image_generator(0, 0)).tolist() == [0, 0, 50, 0]


def test_predict_abstains_on_ties_and_close_counts():
    decide = SmoothedClassifier.decide
    assert decide(np.array([50, 50, 0]), 0.01) == ABSTAIN
    assert decide(np.array([45, 55, 0]), 0.01) == ABSTAIN
    assert decide(np.array([0, 0, 0]), 0.01) == ABSTAIN
    assert decide(np.array([10, 0, 90]), 0.01) == 2
    smoothed = SmoothedClassifier(Constant(1), CameraMotionSmoothing(("rz",), (0.12,)), 4)
    assert smoothed.predict(tiny_sample().renderer(), 100, 0.01, image_generator(0, 3)) == 1
    # With 10 samples PREDICT abstains unless at least 10 agree (binomial p of 9 vs 1 is 0.021 > 0.01);
    # the robot experiment's vote takes the majority and never abstains (ties: the lowest class).
    assert decide(np.array([1, 9, 0]), 0.01) == ABSTAIN and decide(np.array([0, 10, 0]), 0.01) == 1
    assert decide(np.array([1, 9, 0]), 0.01, "vote") == 1
    assert decide(np.array([4, 2, 4]), 0.01, "vote") == 0 and decide(np.array([0, 5, 5]), 0.01, "vote") == 1
    with pytest.raises(ValueError, match="decision rule 'majority'"):
        decide(np.array([1, 2]), 0.01, "majority")


def test_theorem_1_distribution():
    dist = CameraMotionSmoothing(("tx", "ty", "tz", "rz"), (0.05, 0.05, 0.1, 0.122173))
    assert "ellipsoid" in dist.region() and dist.radius(0.99) == pytest.approx(NormalDist().inv_cdf(0.99), abs=1e-12)
    m = dist.sample(20000, image_generator(0, 0))
    assert (m[:, [3, 4]] == 0).all()
    np.testing.assert_allclose(m[:, [0, 1, 2, 5]].std(0).numpy(), [0.05, 0.05, 0.1, 0.122173], rtol=0.03)
    with pytest.raises(MrcertError, match="Theorem 1"):
        CameraMotionSmoothing(("rx", "rz"), (0.1, 0.1))


def certify_rows(outputs: Path) -> pd.DataFrame:
    return concat_logs([read_log(p) for p in sorted(outputs.glob("runs/**/certify.tsv"))]).drop(columns=PER_RUN)


def test_rows_follow_the_formula_and_batch_size_and_shards_do_not_matter(trained, tmp_path):
    base = tmp_path / "base"
    run_task(
        tiny_cfg([*FAST_CERTIFY, f"model.checkpoint={best(trained)}", "task.batch_size=200"], base),
        base / "runs" / "one",
    )
    reference = certify_rows(base)
    assert len(reference) == 6
    for _, row in reference.iterrows():
        # Independent oracles: statsmodels' Clopper-Pearson interval and the standard library's
        # normal distribution (the implementation uses scipy's beta.ppf and norm.ppf).
        p = proportion_confint(row.count_a, row.n, alpha=0.02, method="beta")[0] if row.count_a > 0 else 0.0
        assert row.p_a_lower == pytest.approx(p, abs=1e-12)
        if row.predict == ABSTAIN:
            assert p < 0.5 and row.radius == 0.0
        else:
            assert p >= 0.5 and row.radius == pytest.approx(0.1 * NormalDist().inv_cdf(p), abs=1e-12)
    small = tmp_path / "small"
    run_task(
        tiny_cfg([*FAST_CERTIFY, f"model.checkpoint={best(trained)}", "task.batch_size=7"], small),
        small / "runs" / "one",
    )
    pd.testing.assert_frame_equal(certify_rows(small), reference)
    sharded = tmp_path / "sharded"
    for shard in range(3):
        run_task(
            tiny_cfg(
                [*FAST_CERTIFY, f"model.checkpoint={best(trained)}", f"task.shard={shard}", "task.num_shards=3"],
                sharded,
            ),
            sharded / "runs" / f"s{shard}",
        )
    pd.testing.assert_frame_equal(certify_rows(sharded), reference)


def best(outputs: Path) -> Path:
    (path,) = outputs.glob("runs/train/best.pt")
    return path


@pytest.mark.slow  # the fast suite kills certifications in tests/test_faults.py
def test_certify_killed_and_restarted_resumes_to_the_identical_tsv(trained, tmp_path):
    args = [*TINY, *FAST_CERTIFY, "task.max=8", f"model.checkpoint={best(trained)}"]
    full = tmp_path / "full"
    run_task(tiny_cfg(args[len(TINY) :], full), full / "runs" / "one")
    killed = tmp_path / "killed"

    def two_rows_written() -> bool:
        logs = list(killed.glob("runs/certify/*/certify.tsv"))
        return bool(logs) and len(logs[0].read_text().splitlines()) >= 3  # header + 2 rows

    kill_when(args, killed, two_rows_written)
    (log,) = (tmp_path / "killed").glob("runs/certify/*/certify.tsv")
    assert len(log.read_text().splitlines()) < 9, "the run finished before it could be killed"
    with open(log, "a") as f:
        f.write("7\t1\t0\t0.0")  # a torn last line, as a crash mid-write leaves it
    done = run_cli(args, killed)
    assert done.returncode == 0, done.stderr[-2000:]
    assert list((tmp_path / "killed").glob("runs/certify/*/certify.tsv")) == [log]  # continued in place
    pd.testing.assert_frame_equal(read_log(log).drop(columns=PER_RUN), certify_rows(full))
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'killed' / 'mlflow.db'}")
    (run,) = mlflow.search_runs(search_all_experiments=True, output_format="list")
    assert run.info.status == "FINISHED" and run.data.metrics["num_images"] == 8


def test_import_of_a_hand_written_cohen_log(tmp_path):
    log = tmp_path / "cohen.tsv"
    log.write_text(
        "idx\tlabel\tpredict\tradius\tcorrect\ttime\n"
        "0\t0\t0\t0.5\t1\t0:00:01.0\n"
        "6\t0\t0\t0.05\t1\t0:00:01.0\n"
        "12\t1\t-1\t0.0\t0\t0:00:01.0\n"
        "18\t1\t1\t0.2\t1\t0:00:01.0\n"
        "24\t2\t0\t0.3\t0\t0:00:01.0\n"
    )
    outputs = tmp_path / "out"
    result = run_task(
        tiny_cfg(
            [
                "task=import",
                f"task.path={log}",
                "task.dataset=metaroom",
                "task.arch=resnet50",
                "task.variant=augmented",
                "motion=tz",
            ],
            outputs,
        ),
        outputs / "runs" / "imp",
    )
    assert result["certified_accuracy"] == pytest.approx(2 / 5)  # idx 0 and 18: correct with radius >= 0.1
    assert result["clean_accuracy"] == pytest.approx(3 / 5) and result["abstain_rate"] == pytest.approx(1 / 5)
    mlflow.set_tracking_uri(f"sqlite:///{outputs / 'mlflow.db'}")
    (run,) = mlflow.search_runs(search_all_experiments=True, output_format="list")
    assert run.data.tags["mrcert.dataset"] == "metaroom" and run.data.tags["mrcert.model"] == "resnet50"
    assert run.data.tags["mrcert.variant"] == "augmented" and run.data.tags["mrcert.axis"] == "tz"
    assert run.data.metrics["certified_accuracy"] == pytest.approx(0.4)
    grid = pd.read_csv(Path(run.data.tags["mrcert.output_dir"]) / "certified_accuracy.csv")
    expected = {0.0: 3 / 5, 0.1: 2 / 5, 0.2: 2 / 5, 0.3: 1 / 5, 0.5: 1 / 5}
    for r, acc in expected.items():
        row = grid[np.isclose(grid["radius"], r)]
        assert row["certified_accuracy"].item() == pytest.approx(acc)


def test_result_log_truncates_a_torn_line_and_checks_its_header(tmp_path):
    log = ResultLog(tmp_path / "x.tsv", ["idx", "a", "seconds"], owner={"run_key": "k1", "run_id": None})
    log.append({"idx": 3, "a": 1.5, "seconds": 0.1})
    with open(log.path, "a") as f:
        f.write("4\t2.")
    assert log.done() == {3} and log.path.read_text().endswith("\n")
    with pytest.raises(MrcertError, match="expected idx b seconds check"):
        ResultLog(log.path, ["idx", "b", "seconds"], owner=log.owner).done()
    # A log begun by older code, which wrote fewer columns, resumes: its rows are kept, the new cells empty.
    newer = ResultLog(log.path, ["idx", "a", "seconds", "projected"], owner=log.owner)
    assert newer.done() == {3}
    newer.append({"idx": 5, "a": 2.5, "seconds": 0.2, "projected": 9})
    assert newer.done() == {3, 5}  # the upgraded row carries a check value of its new form
    rows = pd.read_csv(log.path, sep="\t")
    assert (
        rows["idx"].tolist() == [3, 5]
        and rows["a"].tolist() == [1.5, 2.5]
        and rows["projected"].isna().tolist() == [True, False]
    )


@pytest.mark.parametrize(
    "damage,reason",
    [
        ("1\t1\t1\t5.0\n", "cells where the header has"),  # a short row, as a torn write could leave
        ("{row}", "logged twice"),  # a row copied twice
        ("{row_b}", "check value does not match"),  # a row whose value was edited
        ("{other_key}", "check value does not match"),  # a valid row of another run's log
        ("{stranger}", "not one of this run's"),
        ("{mislabelled}", "label 2 where the data set's label of image 4 is 1"),
    ],
)
def test_a_damaged_row_is_set_aside_and_never_adopted(tmp_path, damage, reason):
    """Every row is checked on resume: its cells, its check value (bound to the run key), its
    index and its label. A row that fails is moved to set_aside with its reason, and the image
    is computed again; the valid rows stay."""
    owner = {"run_key": "k1", "run_id": "r1"}
    columns = ["idx", "label", "radius", "seconds"]
    log = ResultLog(tmp_path / "certify.tsv", columns, owner=owner)
    log.append({"idx": 0, "label": 0, "radius": 0.296, "seconds": 1.0})
    first = log.path.read_text().splitlines()[1]
    other = ResultLog(tmp_path / "other.tsv", columns, owner={"run_key": "k2", "run_id": "r2"})
    other.append({"idx": 1, "label": 0, "radius": 5.0, "seconds": 1.0})
    forged = {
        "row": first + "\n",
        "row_b": first.replace("0.296", "5.0") + "\n",
        "other_key": other.path.read_text().splitlines()[1] + "\n",
        "stranger": ResultLog(tmp_path / "s.tsv", columns, owner=owner)._line("9\t0\t5.0\t1.0") + "\n",
        "mislabelled": ResultLog(tmp_path / "m.tsv", columns, owner=owner)._line("4\t2\t5.0\t1.0") + "\n",
    }
    with open(log.path, "a") as f:
        f.write(damage.format(**forged))
    again = ResultLog(log.path, columns, owner=owner)
    assert again.done({0: 0, 1: 0, 4: 1}) == {0}
    assert read_log(log.path, ["idx"]).radius.tolist() == [0.296]
    (aside,) = tmp_path.glob("set_aside/rejected_*/certify.rejected.tsv")
    assert reason in aside.read_text()


def test_smooth_and_attack_tasks(trained, tmp_path):
    ck = f"model.checkpoint={best(trained)}"
    cfg = tiny_cfg(["task=smooth", "task.n=30", "task.max=3", ck], tmp_path)
    smooth = run_task(cfg, tmp_path / "s")
    rows = read_log(tmp_path / "s" / "smooth.tsv", ["idx"])
    # Each row is PREDICT at that test pose, recomputed here through the classifier directly.
    from mrcert.data.sources import load
    from mrcert.infra.checkpoints import load_classifier
    from mrcert.tasks.attack import build_attack

    bundle = load(cfg.data)
    samples = bundle.samples(crop=CameraMotionSmoothing(("tz",), (0.1,)).crop_bound(6.0))
    model = load_classifier(cfg, TINY_CLASSES, "cpu")
    for _, row in rows.iterrows():
        sample = samples[int(row.idx)]
        smoothed = SmoothedClassifier(model, CameraMotionSmoothing(("tz",), (0.1,)), 3)
        assert row.predict == smoothed.predict(sample.renderer(), 30, 0.01, image_generator(0, int(row.idx)))
        assert row.label == sample.label and row.correct == int(row.predict == sample.label)
    assert rows.idx.tolist() == [0, 1, 2] and smooth["num_images"] == 3
    assert smooth["smoothed_benign_accuracy"] == rows.correct.mean()
    assert smooth["abstain_rate"] == (rows.predict == ABSTAIN).mean()
    failures = set()
    # With n = 6 PREDICT cannot decide even when all votes agree (binomial p = 2^-5 > alpha).
    for name, n, most in (("uniform", 20, 18), ("grid", 6, 3)):
        overrides = ["task=attack", f"attack={name}", "attack.k=4", f"task.n={n}", f"task.max={most}", ck]
        out = run_task(tiny_cfg(overrides, tmp_path / name), tmp_path / name / "a")
        df = read_log(next((tmp_path / name / "a").glob("attack.tsv")), ["idx", "base_robust"])
        assert out["base_robust_accuracy"] == df["base_robust"].mean()
        assert (df["base_worst"].abs() <= 0.1).all() and set(df["motion_unit"]) == {"m"}  # tz: metres
        # The smoothed columns, recomputed with PREDICT at each perturbed pose in turn: robust only
        # if right at all K; else the first failing motion and how it failed.
        acfg = tiny_cfg(["task=attack", f"attack={name}", "attack.k=4"], tmp_path / name)
        for _, row in df.iterrows():
            i, render = int(row.idx), samples[int(row.idx)].renderer()
            # The base columns: right at the test pose (benign) and at all K perturbed poses (robust;
            # the test pose is not one of them, so robust can exceed benign).
            motions = build_attack(acfg.attack).motions("tz", int(acfg.seed), i)
            with torch.inference_mode():
                at = model(render(torch.cat([torch.zeros(1, 6, dtype=torch.float64), motions]))).argmax(1)
            assert (row.base_benign, row.base_robust) == (int(at[0] == row.label), int((at[1:] == row.label).all()))
            smoothed = SmoothedClassifier(model, CameraMotionSmoothing(("tz",), (0.1,)), 3)
            expected = (1, "-", None)
            for k, m in enumerate(motions):
                decision = smoothed.predict(render, n, 0.01, image_generator(acfg.seed, i, "predict", k), m)
                if decision != row.label:
                    expected = (0, "abstain" if decision == ABSTAIN else "wrong", float(m[2]))
                    break
            assert (row.smoothed_robust, row.smoothed_failure) == expected[:2]
            assert expected[2] is None or row.smoothed_worst == expected[2]
            failures.add(row.smoothed_failure)
    assert failures == {"-", "abstain", "wrong"}  # every outcome was checked
    grid = read_log(tmp_path / "grid" / "a" / "attack.tsv", ["idx"])
    assert set(np.round(grid["base_worst"], 9)) <= set(np.round(np.linspace(-0.1, 0.1, 4), 9))


@pytest.mark.slow
@pytest.mark.parametrize("axis,sigma", [("tz", 0.1), ("rz", 0.122173), ("rx", 0.0436332)])
def test_soundness_motions_within_the_radius_rarely_change_the_smoothed_prediction(axis, sigma, trained, tmp_path):
    """Across every test image of the scene, on three axes: at motions drawn uniformly within each
    certified radius, PREDICT (n = 2000, alpha = 0.001) names another class than the certificate at a
    rate consistent with at most alpha = 0.01 (one-sided binomial test at the 99% level). An
    abstention is no evidence either way: it is counted apart, and the test requires enough
    decisive trials to detect a flip rate of 10% with probability >= 0.8 (its power, computed)."""
    from scipy.stats import binom, binomtest

    from mrcert.core.axes import axis_index
    from mrcert.data.sources import load
    from mrcert.infra.checkpoints import load_classifier

    cfg = tiny_cfg([*FAST_CERTIFY, f"model.checkpoint={best(trained)}", f"motion={axis}"], tmp_path)
    bundle = load(cfg.data)
    model = load_classifier(cfg, TINY_CLASSES, torch.device("cpu"))
    dist = CameraMotionSmoothing((axis,), (sigma,))
    samples = bundle.samples(crop=dist.crop_bound(6.0))
    flipped, abstained, decisive = 0, 0, 0
    for i in range(len(samples)):
        smoothed, render = SmoothedClassifier(model, dist, 3), samples[i].renderer()
        cert = smoothed.certify(render, 100, 1000, 0.01, image_generator(0, i))
        if cert.prediction == ABSTAIN:
            continue
        rng = np.random.default_rng(i)
        for k, a in enumerate(rng.uniform(-cert.radius, cert.radius, 5)):
            center = torch.zeros(6, dtype=torch.float64)
            center[axis_index(axis)] = a
            pred = smoothed.predict(render, 2000, 0.001, image_generator(1, i, k), center)
            abstained += int(pred == ABSTAIN)
            decisive += int(pred != ABSTAIN)
            flipped += int(pred not in (cert.prediction, ABSTAIN))
    critical = int(binom.ppf(0.99, decisive, 0.01)) + 1  # flips that would reject "rate <= alpha"
    power = float(binom.sf(critical - 1, decisive, 0.10))
    assert power >= 0.8, f"{decisive} decisive trials ({abstained} abstentions): power {power:.2f} too low"
    assert binomtest(flipped, decisive, 0.01, alternative="greater").pvalue > 0.01, (flipped, decisive)


class Brightness(nn.Module):
    """A classifier whose answer depends on the rendered image (how many pixels are not background)."""

    def forward(self, x):
        cls = (x < 1).sum(dim=(1, 2, 3)) % 4
        return torch.nn.functional.one_hot(cls, 4).float()


def test_overlapped_rendering_gives_the_same_votes():
    dist = CameraMotionSmoothing(("rz",), (0.3,))
    plain = SmoothedClassifier(Brightness(), dist, 4, batch_size=100)
    overlapped = SmoothedClassifier(Brightness(), dist, 4, batch_size=100, overlap=True)
    a = plain.sample_counts(tiny_sample().renderer(), 450, image_generator(0, 9))
    b = overlapped.sample_counts(tiny_sample().renderer(), 450, image_generator(0, 9))
    assert a.sum() == 450 and (a > 0).sum() > 1 and np.array_equal(a, b)


class Calls:
    """A render that records the size of every call it gets."""

    def __init__(self, render):
        self.render, self.sizes = render, []

    def __call__(self, motions):
        self.sizes.append(len(motions))
        return self.render(motions)


class Batches(Brightness):
    """:class:`Brightness` recording the size of every batch it classifies."""

    def __init__(self):
        super().__init__()
        self.sizes = []

    def forward(self, x):
        self.sizes.append(len(x))
        return super().forward(x)


@pytest.mark.parametrize("overlap", [False, True])
def test_renders_draw_several_model_batches_at_once_and_give_the_same_votes(overlap):
    """Each render call costs a fixed amount besides its images, so the tasks draw several model
    batches per call (runtime.render_batch); the model still classifies batch by batch, and the
    votes are those of one render per batch."""
    dist = CameraMotionSmoothing(("rz",), (0.3,))
    model = Batches()
    chunked = SmoothedClassifier(model, dist, 4, batch_size=16, overlap=overlap, render_batch=64)
    render = Calls(tiny_sample().renderer())
    votes = chunked.sample_counts(render, 150, image_generator(0, 9))
    assert render.sizes == [64, 64, 22]
    assert model.sizes == [16] * 9 + [6]
    plain = SmoothedClassifier(Brightness(), dist, 4, batch_size=16).sample_counts(
        tiny_sample().renderer(), 150, image_generator(0, 9)
    )
    assert votes.sum() == 150 and (votes > 0).sum() > 1 and np.array_equal(votes, plain)


def test_render_batch_is_whole_model_batches_within_the_pixel_budget():
    assert render_batch(16, 90, 160) == 144  # the quick MetaRoom on a CPU: 9 batches, 2.07M pixels
    assert render_batch(200, 90, 160) == 200  # one batch over the budget is still rendered whole
    assert render_batch(16, 1080, 1920) == 16
    with pytest.raises(ValueError, match="render_batch=40 must be a multiple of batch_size=16"):
        SmoothedClassifier(Brightness(), CameraMotionSmoothing(("rz",), (0.3,)), 4, 16, render_batch=40)


def test_the_tasks_render_several_batches_at_once(trained, tmp_path):
    from mrcert.tasks.evaluation import prepare

    ev = prepare(tiny_cfg(["task=certify", f"model.checkpoint={best(trained)}"], tmp_path))
    votes = ev.smoothed.votes
    assert (ev.bundle.height, ev.bundle.width, votes.batch_size) == (90, 160, 16)  # a CPU's auto batch
    assert votes.render_batch == 144  # 9 model batches: 2.07M pixels, within the 2**21 budget


def test_the_tasks_inference_path_predicts_the_classes_of_the_eager_model(trained, tmp_path):
    """Channels-last weights in small batches (what certify, smooth and attack run) predict,
    sample for sample, the classes of the trained model run eagerly in NCHW on a whole batch,
    from scores equal up to float rounding (the tiny model is confident: its classes alone
    would not tell a lossy path apart)."""
    from mrcert.core.models import build_model
    from mrcert.infra.checkpoints import read_checkpoint
    from mrcert.tasks.evaluation import prepare

    cfg = tiny_cfg(["task=certify", f"model.checkpoint={best(trained)}"], tmp_path)
    ev = prepare(cfg)
    eager = build_model(cfg.model, len(ev.bundle.classes)).eval()
    eager.load_state_dict(read_checkpoint(best(trained))["model"])
    batch = ev.smoothed.votes.batch_size
    with torch.inference_mode():
        for i in ev.indices[:3]:
            images = ev.render(ev.samples[i])(ev.method.sample(100, image_generator(0, i)))
            tasks = torch.cat([ev.model(images[s : s + batch]) for s in range(0, 100, batch)])
            reference = eager(images.contiguous())
            assert torch.equal(tasks.argmax(1), reference.argmax(1))
            torch.testing.assert_close(tasks, reference, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    ("axes", "sigmas", "radius_unit", "sigma_unit"),
    [
        (("tz",), (0.1,), "m", "m"),
        (("ry",), (0.1,), "rad", "rad"),
        (("tx", "ty", "tz", "rz"), (0.1, 0.1, 0.2, 0.05), "sigma", "m+m+m+rad"),
    ],
)
def test_a_certificate_carries_the_unit_of_its_radius(axes, sigmas, radius_unit, sigma_unit):
    """One axis: its unit (metres for t*, radians for r*, by the axis's place in the motion
    vector); several: Theorem 1's ellipsoid, whose radius is in sigma units."""
    dist = CameraMotionSmoothing(axes, sigmas)
    cert = SmoothedClassifier(Constant(2), dist, 4).certify(
        tiny_sample().renderer(), 8, 40, 0.01, image_generator(0, 0)
    )
    assert cert.unit == dist.region_unit == dist.view_unit == radius_unit and dist.sigma_unit == sigma_unit
    assert f"({radius_unit})" in dist.region() if len(axes) == 1 else "sigma units" in dist.region()


def test_sequential_smooth_and_attack_are_predict_sequential_at_each_pose_whatever_the_batch(trained, tmp_path):
    """task.sequential=true: each smooth row is sequential PREDICT at the test pose (its n column
    the samples drawn, one of the design's looks), each attack row's smoothed columns are
    sequential PREDICT at each perturbed pose in turn; the same rows in batches of 8 and 64."""
    from mrcert.core.sequential import PredictDesign
    from mrcert.data.sources import load
    from mrcert.infra.checkpoints import load_classifier
    from mrcert.tasks.attack import build_attack

    ck = f"model.checkpoint={best(trained)}"
    logs = {}
    for batch in (8, 64):
        cfg = tiny_cfg(["task=smooth", "task.sequential=true", "task.max=3", f"task.batch_size={batch}", ck], tmp_path)
        run_task(cfg, tmp_path / f"s{batch}")
        overrides = ["task=attack", "attack.k=4", "task.sequential=true", "task.max=4", f"task.batch_size={batch}", ck]
        run_task(tiny_cfg(overrides, tmp_path / f"a{batch}"), tmp_path / f"a{batch}" / "a")
        logs[batch] = (
            read_log(tmp_path / f"s{batch}" / "smooth.tsv", ["idx"]),
            read_log(tmp_path / f"a{batch}" / "a" / "attack.tsv", ["idx"]),
        )
    for a, b in zip(logs[8], logs[64], strict=True):
        kept = [c for c in a.columns if c not in PER_RUN]
        pd.testing.assert_frame_equal(a[kept], b[kept])
    rows, attacked = logs[8]
    design = PredictDesign.plan(100, 0.01, 20)
    assert set(rows["n"]) <= set(design.looks)
    bundle = load(cfg.data)
    samples = bundle.samples(crop=CameraMotionSmoothing(("tz",), (0.1,)).crop_bound(6.0))
    smoothed = SmoothedClassifier(load_classifier(cfg, TINY_CLASSES, "cpu"), CameraMotionSmoothing(("tz",), (0.1,)), 3)
    for _, row in rows.iterrows():
        decision, votes = smoothed.predict_sequential(
            samples[int(row.idx)].renderer(), 100, 0.01, 20, image_generator(0, int(row.idx))
        )
        assert (row.predict, row.n) == (decision, votes.sum())
    acfg = tiny_cfg(["task=attack", "attack.k=4"], tmp_path)
    for _, row in attacked.iterrows():
        i, render = int(row.idx), samples[int(row.idx)].renderer()
        expected = (1, "-")
        for k, m in enumerate(build_attack(acfg.attack).motions("tz", int(acfg.seed), i)):
            decision, _ = smoothed.predict_sequential(
                render, 100, 0.01, 20, image_generator(acfg.seed, i, "predict", k), m
            )
            if decision != row.label:
                expected = (0, "abstain" if decision == ABSTAIN else "wrong")
                break
        assert (row.smoothed_robust, row.smoothed_failure) == expected


@pytest.mark.parametrize("name", ["uniform", "grid"])
def test_each_attack_is_the_class_its_yaml_names_and_tries_k_motions_on_its_axis(name):
    """``attack=...`` builds the class of its ``_target_``: K motions on the run's axis alone,
    within [-r, r]; the grid evenly spaced from -r to r, the uniform draws seeded per image."""
    from mrcert.core import attacks
    from mrcert.tasks.attack import build_attack

    cfg = compose_cfg(["task=attack", f"attack={name}", "attack.k=7", "attack.radius=0.02", "motion=tz"])
    attack = build_attack(cfg.attack)
    assert type(attack) is {"uniform": attacks.Uniform, "grid": attacks.Grid}[name]
    motions = attack.motions("tz", 0, 3)
    assert motions.shape == (7, 6) and (motions[:, [0, 1, 3, 4, 5]] == 0).all()
    assert (motions[:, 2].abs() <= 0.02).all()
    again, other = attack.motions("tz", 0, 3), attack.motions("tz", 0, 4)
    assert torch.equal(motions, again)
    if name == "grid":
        assert torch.equal(motions[:, 2], torch.linspace(-0.02, 0.02, 7, dtype=torch.float64)) and torch.equal(
            motions, other
        )
    else:
        assert not torch.equal(motions, other)
