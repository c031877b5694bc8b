"""The verification community's formats: ONNX classifiers and VNN-LIB properties read and written,
``task=verify`` answering as the competition's tools do, and ``task=export`` writing instances
that it (or another verifier) can check."""

import gzip
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from onnx import numpy_helper
from torch import nn

from mrcert.core.models import Normalize, SmallCNN
from mrcert.core.verification.network import BoundNetwork
from mrcert.errors import MrcertError
from mrcert.formats.onnx_model import read_onnx, write_onnx
from mrcert.formats.vnnlib import read_vnnlib, write_vnnlib
from tests.conftest import ROOT, TINY, run_cli, store_runs

BENCH = ROOT / "tests" / "data" / "metaroom_vnncomp"
ONNX = BENCH / "onnx" / "4cnn_ry_33_5_no_custom_OP.onnx.gz"


def unzipped(path: Path, folder: Path) -> Path:
    out = folder / path.with_suffix("").name
    out.write_bytes(gzip.decompress(path.read_bytes()))
    return out


def test_the_competition_network_reads_as_the_cnn_it_describes(tmp_path):
    """The 4-layer MetaRoom CNN read from ONNX computes what the same weights do in a plain
    torch model written from its description (conv 3->8 4x4 s2 p1, ReLU, conv 8->16, ReLU,
    flatten, linear 1792->256, ReLU, linear 256->20), and bound propagation reads it too."""
    import onnx

    path = unzipped(ONNX, tmp_path)
    weights = {t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in onnx.load(path).graph.initializer}
    plain = nn.Sequential(
        nn.Conv2d(3, 8, 4, 2, 1), nn.ReLU(), nn.Conv2d(8, 16, 4, 2, 1), nn.ReLU(), nn.Flatten(),
        nn.Linear(1792, 256), nn.ReLU(), nn.Linear(256, 20),
    )  # fmt: skip
    for module, name in ((plain[0], "conv1"), (plain[2], "conv2"), (plain[5], "fc1"), (plain[7], "fc2")):
        module.weight.data, module.bias.data = weights[f"{name}.weight"], weights[f"{name}.bias"]
    net = read_onnx(path)
    x = torch.rand(4, 3, 32, 56, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert torch.allclose(net(x), plain(x), atol=1e-5)
    assert [layer.kind for layer in BoundNetwork(net).layers].count("relu") == 3


def test_our_classifier_survives_the_round_trip_through_onnx(tmp_path):
    model = nn.Sequential(Normalize(), SmallCNN(5, 8)).eval()
    back = read_onnx(write_onnx(model, (3, 20, 32), tmp_path / "m.onnx"))
    x = torch.rand(3, 3, 20, 32, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert torch.allclose(back(x), model(x), atol=1e-5)


def test_a_property_survives_the_round_trip_bit_for_bit(tmp_path):
    rng = np.random.default_rng(0)
    low = rng.uniform(0, 1, 50)
    high = low + rng.uniform(0, 1e-7, 50) * (rng.uniform(size=50) < 0.5)
    prop = read_vnnlib(write_vnnlib(tmp_path / "p.vnnlib", low, high, 2, 4))
    assert np.array_equal(prop.low, low) and np.array_equal(prop.high, high)
    assert len(prop.unsafe) == 3 and prop.violated(np.array([0.0, 1.0, 1.0, 0.0])) and not prop.violated(np.eye(4)[2])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("(declare-const X_0 Real)\n(declare-const Y_0 Real)\n(assert (<= Y_0 0))", "every input needs"),
        (
            "(declare-const X_0 Real)\n(declare-const Y_0 Real)\n(assert (<= X_0 1))\n(assert (>= X_0 0))",
            "no output constraint",
        ),
        ("(declare-const X_0 Real)\n(assert (<= X_0 1)", "unbalanced"),
        (
            "(declare-const X_0 Real)(declare-const Y_0 Real)(assert (or (and (<= X_0 1) (>= X_0 Y_0))))",
            "inputs with outputs",
        ),
    ],
)
def test_a_property_it_cannot_read_is_refused_in_one_line(tmp_path, text, message):
    (tmp_path / "p.vnnlib").write_text(text)
    with pytest.raises(MrcertError, match=message):
        read_vnnlib(tmp_path / "p.vnnlib")


def test_verify_answers_the_competition_instances_as_its_tools_did(tmp_path):
    """spec_idx_11, which the competition's tools falsified, is ``sat`` with a counterexample
    inside the box that the network classifies into the unsafe region; spec_idx_40, which they
    verified, is ``unsat``."""
    done = run_cli(["task=verify", f"task.instances={BENCH / 'instances.csv'}", "task.timeout=120"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    (run,) = sorted((tmp_path / "runs" / "verify").iterdir())
    log = pd.read_csv(run / "verify.tsv", sep="\t")
    assert log["result"].tolist() == ["sat", "unsat"]
    text = (run / "results" / "0.txt").read_text().splitlines()
    assert text[0] == "sat"
    values = {k: float(v) for k, v in (line.strip(" ()").split() for line in text[1:] if line.strip(" ()"))}
    prop = read_vnnlib(unzipped(BENCH / "vnnlib" / "spec_idx_11_eps_0.00000436.vnnlib.gz", tmp_path))
    x = np.array([values[f"X_{i}"] for i in range(prop.low.size)])
    assert ((x >= prop.low) & (x <= prop.high)).all()
    with torch.no_grad():
        y = read_onnx(unzipped(ONNX, tmp_path))(torch.from_numpy(x).float().reshape(1, 3, 32, 56))[0].numpy()
    assert prop.violated(y)
    assert np.allclose(y, [values[f"Y_{j}"] for j in range(20)], atol=1e-4)
    assert (run / "results" / "1.txt").read_text() == "unsat\n"
    # The comparison beside the competition's tools prints the command as it was typed.
    comparison = (run / "comparison.md").read_text()
    typed = f"mrcert task=verify task.instances={BENCH / 'instances.csv'} task.timeout=120"
    assert f"```bash\n{typed}\n```" in comparison and "_target_" not in comparison


def test_verify_refuses_missing_inputs_before_any_run(tmp_path):
    done = run_cli(["task=verify"], tmp_path)
    assert done.returncode != 0 and "task.onnx and task.vnnlib, or task.instances" in done.stderr
    listing = tmp_path / "instances.csv"
    listing.write_text("onnx/none.onnx,vnnlib/none.vnnlib,10\n")
    done = run_cli(["task=verify", f"task.instances={listing}"], tmp_path)
    assert done.returncode != 0 and "none.onnx" in done.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "mlflow.db").exists() or not store_runs(tmp_path)  # no run was opened


@pytest.mark.slow
def test_exported_instances_hold_every_image_of_their_piece_and_verify_back(tmp_path):
    """``task=export`` on a tiny model: the ONNX file computes the checkpoint's logits, every
    property's box holds the images rendered at poses of its piece, and ``task=verify`` answers
    every instance."""
    from mrcert.__main__ import run_task
    from mrcert.infra.checkpoints import load_classifier
    from mrcert.tasks.evaluation import prepare
    from tests.conftest import compose_cfg

    models = tmp_path / "store"
    run_task(compose_cfg([*TINY, "task=train", "train.epochs=1", "train.batch_size=8"], models), models / "a")
    common = [*TINY, f"model.checkpoint={models / 'a' / 'best.pt'}", "motion.radius=0.001", "task.max=2"]
    done = run_cli(["task=export", "task.pieces=2", "task.timeout=30", *common], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    (run,) = sorted((tmp_path / "runs" / "export").iterdir())
    rows = (run / "instances.csv").read_text().split()
    assert len(rows) == 4
    cfg = compose_cfg(["task=certify", "method=bound_propagation", *common], tmp_path)
    ev = prepare(cfg)
    net = read_onnx(run / "model.onnx")
    model = load_classifier(cfg, ev.bundle.classes, torch.device("cpu"))
    for i in ev.indices:
        render = ev.samples[i].renderer()
        for piece, (start, end) in enumerate(((-0.001, 0.0), (0.0, 0.001))):
            prop = read_vnnlib(run / "vnnlib" / f"image_{i}_piece_{piece}.vnnlib")
            motions = torch.zeros(50, 6, dtype=torch.float64)
            motions[:, 2] = torch.linspace(start, end, 50, dtype=torch.float64)
            images = render(motions)
            flat = images.double().flatten(1).numpy()
            assert ((flat >= prop.low) & (flat <= prop.high)).all()
            with torch.no_grad():
                assert torch.allclose(net(images), model(images), atol=1e-4)
    done = run_cli(["task=verify", f"task.instances={run / 'instances.csv'}"], tmp_path / "v")
    assert done.returncode == 0, done.stderr[-2000:]
    (checked,) = sorted((tmp_path / "v" / "runs" / "verify").iterdir())
    assert set(pd.read_csv(checked / "verify.tsv", sep="\t")["result"]) <= {"unsat", "sat", "unknown", "timeout"}


def test_the_verification_page_states_what_the_reader_reads_and_refuses():
    """docs/verification.md's section on what is read is the one the reader's own tables give,
    with the limits task=verify's config sets, and its harness section is the one the code states."""
    from omegaconf import OmegaConf

    from mrcert.formats.onnx_model import MAX_MODEL_BYTES
    from mrcert.formats.vnnlib import MAX_PROPERTY_BYTES
    from mrcert.tasks.verify import harness_section, reading_section

    page = (ROOT / "docs" / "verification.md").read_text()
    assert reading_section() in page and harness_section() in page
    conf = OmegaConf.load(ROOT / "conf" / "task" / "verify.yaml")
    assert conf.max_model_mb * 2**20 == MAX_MODEL_BYTES and conf.max_property_mb * 2**20 == MAX_PROPERTY_BYTES
