"""Run identity: every config key is classified, and the run key moves with exactly the
result-defining keys of each task."""

import copy
import re

import pytest

from mrcert.infra.config import CONF_DIR, plain
from mrcert.infra.identity import file_identity, flatten, identify
from mrcert.infra.tasks import TASKS
from tests.conftest import ROOT, compose_cfg

REQUIRED = {"import": ["task.path=certify.tsv"]}
EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
DATA = sorted(p.stem for p in (CONF_DIR / "data").glob("*.yaml"))
BOUND = "runs:/0123456789abcdef/checkpoints/best.pt"


def composed(task: str, *extra: str) -> dict:
    cfg = plain(compose_cfg([f"task={task}", *REQUIRED.get(task, []), *extra]))
    if TASKS[task].identity.needs_model:
        cfg["model"]["checkpoint"] = BOUND  # what binding does before a key exists
    return cfg


def set_key(cfg: dict, dotted: str, value) -> dict:
    """A copy of ``cfg`` with the leaf at ``dotted`` replaced (keys may contain dots: ``mrcert.task``)."""
    out = copy.deepcopy(cfg)
    node, rest = out, dotted
    while True:
        if isinstance(node, list):
            head, _, rest = rest.partition(".")
            if not rest:
                node[int(head)] = value
                return out
            node = node[int(head)]
            continue
        if rest in node:
            node[rest] = value
            return out
        head = next(k for k in node if rest.startswith(k + "."))
        node, rest = node[head], rest[len(head) + 1 :]


def changed(value):
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, list):
        return [*value, "x"]
    return f"{value}x"


@pytest.mark.parametrize("data", DATA)
@pytest.mark.parametrize("task", list(TASKS))
def test_every_key_of_every_shipped_config_is_classified(task, data):
    cfg = composed(task, f"data={data}")
    identity = TASKS[task].identity
    unclassified = [k for k in flatten(cfg) if identity.classify(k, identity.ignored(cfg)) is None]
    assert unclassified == []


RUNS_ANYWHERE = (
    "paths",
    "tracking",
    "device",
    "skip_finished",
    "data.cache_dir",
    "data.extent",
    "per_task",
    "task._target_",
    "attack._target_",
    "data._target_",
)
"""Where outputs go, how runs are tracked and scheduled, a bound only validation reads, an
experiment's settings of single tasks (what they set is in the task's own keys), and the class
that runs the task (its name, in the key, says which)."""
HOW_IT_EVALUATES = ("task.batch_size", "task.backend", "task.resume", "task.crop_sigmas")
"""How an evaluation computes, never what: batches, the projection's back end, resuming, the exact crop."""


def defines_the_result(task: str, cfg: dict, key: str) -> bool:
    """Whether ``key`` defines ``task``'s result for ``cfg``: the specification, written out here
    (not read from the task table, which it checks)."""

    def under(*prefixes: str) -> bool:
        return any(key == p or key.startswith(p + ".") for p in prefixes)

    if under(*RUNS_ANYWHERE) or (cfg["method"]["name"] == "camera_motion" and under("method") and key != "method.name"):
        return False  # camera motion smoothing's parameters are all in motion.* (its name says which method)
    if task in ("import", "gather"):
        return under("task")
    if task == "ui":  # no run and no result: serving the store depends on nothing a key holds
        return key == "task.name"
    if task == "verify":  # its instances and how it verifies them; not where it also writes answers
        return under("task") and not under("task.page", "task.result")
    if task == "tables":
        return under("task", "profile")
    if task == "render":
        return not under("model", "train", "attack", "task.backend")
    if task == "viewpoints":
        return not under("train", "model.trained_for", "attack", "motion", "method", "task.batch_size")
    if task == "train":  # the recipe, the data, the model and what it is augmented with
        if under("task"):
            return key == "task.name"
        vanilla = cfg["model"]["variant"] == "vanilla"
        pixel_noise = cfg["method"]["name"] == "pixelwise"  # one pixel-noise model serves every axis
        unseen = under("motion") and (vanilla or pixel_noise) or under("method") and vanilla
        return not (under("model.checkpoint", "model.trained_for", "attack", "method.certify") or unseen)
    # certify, smooth, attack: an evaluation of a trained model (named by its checkpoint, which
    # says how and for which method it was trained)
    if under("train", "model.trained_for", *HOW_IT_EVALUATES) or (under("attack") and task != "attack"):
        return False
    if task == "export" and under("task.sequential", "task.look"):
        return False  # it samples nothing
    return not (key == "task.look" and not cfg["task"]["sequential"])  # fixed n has no looks


@pytest.mark.parametrize("method", ["camera_motion", "pixelwise"])
@pytest.mark.parametrize("variant", ["vanilla", "augmented"])
@pytest.mark.parametrize("task", list(TASKS))
def test_the_run_key_changes_with_every_defining_key_and_no_other(task, variant, method):
    cfg = composed(task, f"model.variant={variant}", f"method={method}")
    identity = TASKS[task].identity
    base = identify(cfg, identity)
    wrong = []
    for key, value in flatten(cfg).items():
        defining = defines_the_result(task, cfg, key)
        if (identify(set_key(cfg, key, changed(value)), identity).key != base.key) != defining:
            wrong.append((key, "defining" if defining else "ignored"))
    assert wrong == []


def test_what_defines_a_result_and_what_does_not():
    certify = composed("certify")
    key = lambda cfg, task="certify": identify(cfg, TASKS[task].identity)  # noqa: E731
    # Result-defining: the model, the images, the statistics.
    for dotted, value in [
        ("model.checkpoint", "runs:/fedcba/checkpoints/best.pt"),
        ("task.max", 2),
        ("task.alpha", 0.05),
        ("task.n", 10),
        ("seed", 1),
        ("motion.sigma", 0.2),
    ]:
        assert key(set_key(certify, dotted, value)).key != key(certify).key, dotted
    # How and where it runs: never.
    for dotted, value in [
        ("task.batch_size", 7),
        ("task.backend", "torch"),
        ("device", "cpu"),
        ("task.resume", False),
        ("paths.outputs", "/elsewhere"),
        ("data.cache_dir", "/c"),
        ("tracking.uri", "http://x"),
        ("train.epochs", 3),
        ("skip_finished", True),
    ]:
        assert key(set_key(certify, dotted, value)).key == key(certify).key, dotted
    # Shards split one result: a shard has its own run key but the cell key of the whole.
    shard = set_key(set_key(certify, "task.num_shards", 4), "task.shard", 2)
    assert key(shard).key != key(certify).key and key(shard).cell == key(certify).cell
    # A vanilla model never sees the motion; an augmented one is defined by it.
    vanilla, augmented = composed("train"), composed("train", "model.variant=augmented")
    assert key(set_key(vanilla, "motion.sigma", 0.3), "train").key == key(vanilla, "train").key
    assert key(set_key(augmented, "motion.sigma", 0.3), "train").key != key(augmented, "train").key
    assert key(set_key(vanilla, "train.lr", 0.5), "train").key != key(vanilla, "train").key
    # Fixed-n CERTIFY has no looks; a sequential one is defined by them.
    sequential = set_key(certify, "task.sequential", True)
    assert key(set_key(certify, "task.look", 20)).key == key(certify).key
    assert key(set_key(sequential, "task.look", 20)).key != key(sequential).key != key(certify).key


@pytest.mark.parametrize("task", list(TASKS))
def test_a_new_scene_generator_makes_new_runs(task, monkeypatch):
    """Runs of an older scene generator (GENERATOR_VERSION) are another result: neither skipped
    as finished nor resumed, nor read into a table, by today's code."""
    import mrcert.infra.identity as identity_module

    cfg = composed(task)
    before = identify(cfg, TASKS[task].identity)
    monkeypatch.setattr(identity_module, "GENERATOR_VERSION", identity_module.GENERATOR_VERSION + 1)
    after = identify(cfg, TASKS[task].identity)
    assert after.key != before.key and after.cell != before.cell


def test_a_checkpoint_file_is_identified_by_its_content(tmp_path):
    a, b, c = tmp_path / "a.pt", tmp_path / "b.pt", tmp_path / "c.pt"
    a.write_bytes(b"weights")
    b.write_bytes(b"weights")
    c.write_bytes(b"other weights")
    assert file_identity(str(a)) == file_identity(str(b)) != file_identity(str(c))
    assert file_identity(BOUND) == BOUND
    certify = composed("certify")
    keys = {p: identify(set_key(certify, "model.checkpoint", str(p)), TASKS["certify"].identity) for p in (a, b, c)}
    assert keys[a].key == keys[b].key != keys[c].key
    assert keys[a].checkpoint == file_identity(str(a)) and keys[a].checkpoint.startswith("sha256:")


@pytest.mark.parametrize("experiment", EXPERIMENTS)
@pytest.mark.parametrize("task", ["train", "certify", "smooth", "attack"])
def test_experiments_set_no_key_that_the_task_does_not_have(experiment, task):
    own = set(compose_cfg([f"task={task}"]).task)
    assert set(compose_cfg([f"experiment={experiment}", f"task={task}"]).task) == own


def test_one_module_decides_which_run_serves_a_job():
    """A run key's finished or interrupted runs, a model's newest train run and the finished runs
    the tables index are asked of :mod:`mrcert.infra.run_store` alone: no other module filters
    the store by run key or status. (A sweep's bookkeeping -- its parent's children, parents'
    tags -- queries by parent, not to pick a run.)"""
    asks = re.compile(r"mrcert\.key`\s*=|attributes\.status\s*[!=]=?\s*'FINISHED'|\.search_runs\(")
    bookkeeping = {"mrcert/infra/sweeps.py", "mrcert/infra/experiment.py"}
    found = {
        str(p.relative_to(ROOT)): asks.findall(p.read_text())
        for p in (ROOT / "mrcert").rglob("*.py")
        if p.name != "run_store.py"
    }
    assert {path for path, hits in found.items() if hits} == bookkeeping
    for path in bookkeeping:
        assert found[path] == [".search_runs("], path
