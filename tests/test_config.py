"""Every option of every config group composes and validates; bad values are named."""

import dataclasses
from collections.abc import Mapping
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, ValidationError

from mrcert.errors import ConfigError
from mrcert.infra.config import CONF_DIR, plain, validate
from mrcert.infra.identity import flatten
from tests.conftest import run_cli

GROUPS = sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and p.name != "hydra")


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def compose_cfg(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=overrides, return_hydra_config=True)


REQUIRED = {
    ("data", "pointcloud"): ["data.path=scan.ply"],
    ("data", "custom"): ["data.path=scan.ply", "data.poses=poses.json"],
    ("task", "import"): ["task.path=certify.tsv"],
    ("task", "gather"): ["task.store=other/outputs"],
}


def option_file(group: str, option: str) -> tuple[str, dict]:
    """The package an option's file writes to and its own values (defaults list left out)."""
    path = CONF_DIR / group / f"{option}.yaml"
    first = path.read_text().splitlines()[0]
    package = first.split("@package", 1)[1].strip() if "@package" in first else group
    values = yaml.safe_load(path.read_text()) or {}
    values.pop("defaults", None)
    return package, values


@pytest.mark.parametrize("group,option", [(g, o) for g in GROUPS for o in options(g)])
def test_every_option_composes_to_its_own_values_and_validates(group, option):
    cfg = compose_cfg([f"{group}={option}", *REQUIRED.get((group, option), [])])
    assert cfg.hydra.runtime.choices[group] == option
    package, values = option_file(group, option)
    node = cfg if package == "_global_" else OmegaConf.select(cfg, package)
    literal = {k: v for k, v in flatten(values).items() if not (isinstance(v, str) and ("${" in v or v == "???"))}
    composed = flatten(OmegaConf.to_container(node, resolve=False))
    # Every value the file sets is in the composed config, unless an option composed later overrides it.
    overridden = {k for k in literal if composed.get(k) != literal[k]}
    assert overridden <= later_overrides(cfg, group, package), overridden
    validate(cfg)
    assert OmegaConf.select(cfg, "hydra.run.dir").startswith(str(cfg.paths.outputs))


def _defaults_order() -> list[str]:
    """The config groups in the order conf/config.yaml's defaults list composes them."""
    entries = OmegaConf.load(CONF_DIR / "config.yaml").defaults
    groups = [next(iter(e)) if isinstance(e, Mapping) else str(e) for e in entries]
    return [g.removeprefix("optional ") for g in groups if g != "_self_"]


DEFAULTS_ORDER = _defaults_order()


def later_overrides(cfg, group: str, package: str) -> set[str]:
    """Keys (relative to ``package``) that options composed after ``group`` set."""
    order = DEFAULTS_ORDER
    keys: set[str] = set()
    for later in order[order.index(group) + 1 :] if group in order else []:
        choice = cfg.hydra.runtime.choices.get(later)
        if not choice or not (CONF_DIR / later / f"{choice}.yaml").is_file():  # an optional group left out
            continue
        later_package, values = option_file(later, choice)
        for k in flatten(values):
            full = k if later_package == "_global_" else f"{later_package}.{k}"
            if package == "_global_":
                keys.add(full)
            elif full.startswith(package + "."):
                keys.add(full[len(package) + 1 :])
    return keys


def test_groups_the_issue_asks_for_exist():
    assert {"task", "data", "motion", "model", "attack", "tracking"} <= set(GROUPS)
    assert {"tx", "ty", "tz", "rx", "ry", "rz"} <= set(options("motion"))
    assert options("tracking") == ["off", "server", "sqlite"]


def test_the_learning_curve_reaches_the_training_poses_of_the_page_s_models():
    """The evidence page's curve must say what the data its Table 3 models train on gives: its sweep
    covers experiment=reproduce_quick's training poses per class, on the same data and model."""
    results = compose_cfg(["experiment=reproduce_quick"])
    curve = compose_cfg(["experiment=learning_curve"])
    swept = str(curve.hydra.sweeper.params["data.protocol.train.per_class"]).split(",")
    assert str(results.data.protocol.train.per_class) in swept, (results.data.protocol.train.per_class, swept)
    assert (curve.data.name, curve.model.arch, curve.model.net.width) == (
        results.data.name,
        results.model.arch,
        results.model.net.width,
    )


def test_the_learning_curve_s_architectures_differ_in_the_model_alone():
    """Every experiment the page's learning curve reads trains a vanilla model on the same data,
    protocol and recipe as the small CNN's curve, on training poses that curve also has, under
    one of the two separation rules, so that its rows differ from that curve's in the
    architecture or the rule and nothing else."""
    from mrcert.reporting.learning_curve import EXPERIMENTS

    base = compose_cfg([f"experiment={EXPERIMENTS[0]}"])
    poses = set(str(base.hydra.sweeper.params["data.protocol.train.per_class"]).split(","))
    archs = set()
    for experiment in EXPERIMENTS:
        cfg = compose_cfg([f"experiment={experiment}"])
        params = cfg.hydra.sweeper.params
        assert set(str(params["data.protocol.train.per_class"]).split(",")) <= poses, experiment
        assert str(params["data.protocol.separation_rule"]) in ("every", "any"), experiment
        assert cfg.data == base.data and cfg.train == base.train and cfg.model.variant == "vanilla", experiment
        archs.add(cfg.model.arch)
    assert archs == {"small_cnn", "resnet18"}


@pytest.mark.parametrize(
    "axis,sigma", [("tz", 0.1), ("tx", 0.05), ("ty", 0.05), ("rz", 0.122173), ("rx", 0.0436332), ("ry", 0.0436332)]
)
def test_motion_configs_carry_the_paper_numbers(axis, sigma):
    m = compose_cfg([f"motion={axis}"]).motion
    assert (m.axis, m.sigma, m.radius) == (axis, sigma, sigma)
    assert m.radius_step == pytest.approx(sigma / 10)


def test_default_store_is_an_absolute_sqlite_uri_under_outputs():
    cfg = compose_cfg([])
    uri = cfg.tracking.uri
    assert uri.startswith("sqlite:////") and uri.endswith("/outputs/mlflow.db")
    assert Path(cfg.tracking.artifact_location).is_absolute()


def test_evaluation_batches_suit_the_device_unless_given():
    """By default a GPU classifies 200 samples at once and a CPU 16 (docs/performance.md); a number
    given is used as is, on any device."""
    from mrcert.infra.runtime import batch_size

    default = compose_cfg(["task=certify"]).task.batch_size
    assert batch_size(default, torch.device("cuda")) == 200 and batch_size(default, torch.device("cpu")) == 16
    given = compose_cfg(["task=certify", "task.batch_size=7"]).task.batch_size
    assert batch_size(given, torch.device("cuda")) == batch_size(given, torch.device("cpu")) == 7


@pytest.mark.parametrize(
    "override,key,value,allowed",
    [
        ("motion.axis=tw", "motion.axis", "'tw'", "tx, ty, tz, rx, ry, rz"),
        ("motion.sigma=0", "motion.sigma", "0", "> 0"),
        ("motion.sigma=-0.1", "motion.sigma", "-0.1", "> 0"),
        ("motion.radius=-1", "motion.radius", "-1", ">= 0"),
        ("task=certify task.alpha=1.5", "task.alpha", "1.5", "strictly between 0 and 1"),
        ("task=certify task.alpha=0", "task.alpha", "0", "strictly between 0 and 1"),
        ("data.image.height=0", "data.image.height", "0", "integer >= 1"),
        ("data.image.width=0", "data.image.width", "0", "integer >= 1"),
        ("data.image.fx=-3", "data.image.fx", "-3", "> 0"),
        ("task.axes=[tx,up]", "task.axes", "['tx', 'up']", "list of axes"),
        ("device=gpu", "device", "'gpu'", "auto, cpu, or a GPU of this machine"),
        ("device=cuda:7", "device", "'cuda:7'", "auto, cpu, or a GPU of this machine"),
        ("seed=18446744073709551616", "seed", "18446744073709551616", "an integer in [0, 2**32)"),
        (
            "data.classes=[mug,mug,can]",
            "data.classes",
            "['mug', 'mug', 'can']",
            "a non-empty list of class names, each once",
        ),
        ("task=certify task.batch_size=big", "task.batch_size", "'big'", "an integer >= 1, or auto"),
        ("task=certify task.batch_size=0", "task.batch_size", "0", "an integer >= 1, or auto"),
        ("task=certify task.sequential=true task.n=30", "task.look", "40", "an integer in [1, task.n=30]"),
        # Values of nodes whose shape is not a structured config's, checked by a schema all the same.
        ("data.protocol.train.per_class=0", "data.protocol.train.per_class", "0", "an integer >= 1"),
        ("data.protocol.train.yaw_range=[2,1]", "data.protocol.train.yaw_range", "[2, 1]", "low <= high"),
        ("data.protocol.separation.yaw=-1", "data.protocol.separation.yaw", "-1", "a finite number >= 0"),
        ("data.protocol.separation_rule=some", "data.protocol.separation_rule", "'some'", "every or any"),
        ("+per_task.attack.skip=0", "per_task.attack.skip", "0", "an integer >= 1"),
        ("model.trained_for={name:pixelwise,sigma:0}", "model.trained_for.sigma", "0", "a finite number > 0"),
        ("model=small_cnn model.net.width=0", "model.net.width", "0", "an integer >= 1"),
    ],
)
def test_bad_values_are_rejected_with_key_value_and_allowed(override, key, value, allowed):
    cfg = compose_cfg(override.split())
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    message = str(info.value)
    assert f"{key}={value}" in message and allowed in message


CHECKED_COMPOSITIONS = [
    *([f"task={t}", *REQUIRED.get(("task", t), [])] for t in options("task")),
    *([f"data={d}", *REQUIRED.get(("data", d), [])] for d in options("data")),
    ["motion=txyz_rz"],
    ["method=pixelwise"],
    ["method=bound_propagation"],
    ["method=enumeration"],
]
CANDIDATES = [-1, 0, 1, 0.5, 1.5, 2.0, 2**40, -0.5, float("inf"), "x", None, [], [1.0, 0.0], ["x"]]


def test_every_check_a_schema_declares_refuses_a_bad_value_naming_its_key():
    """Each checked field of every schema a config composes is checked on it: a value its type
    holds but its check refuses (taken from a fixed list) fails validation, naming that key."""
    from mrcert.core.checks import field_checks
    from mrcert.infra.config import structured_nodes
    from mrcert.infra.schema import SCHEMAS

    def with_nested(schema):
        yield schema
        for f in dataclasses.fields(schema):
            if dataclasses.is_dataclass(f.default_factory):
                yield from with_nested(f.default_factory)

    every = {s for group in SCHEMAS.values() for schema in group.values() for s in with_nested(schema)}
    declared = {(schema.__name__, name) for schema in every for name, _ in field_checks(schema)}
    tried = set()
    for overrides in CHECKED_COMPOSITIONS:
        cfg = compose_cfg(overrides)
        for schema, where in (n for group in cfg if group != "hydra" for n in structured_nodes(cfg, group)):
            for name, check in ((n, c) for n, c in field_checks(schema) if (schema.__name__, n) not in tried):
                for value in (v for v in CANDIDATES if not check.holds(v)):
                    bad = cfg.copy()
                    try:
                        OmegaConf.update(bad, f"{where}.{name}", value, merge=False)
                    except ValidationError:
                        continue  # its type cannot hold it: refused at composition
                    if OmegaConf.select(bad, f"{where}.{name}") != value:
                        continue  # converted to a value of its type
                    with pytest.raises(ConfigError) as info:
                        validate(bad)
                    # That key, or one whose value is that key's (an interpolation) and is checked first.
                    named = info.value.key == f"{where}.{name}" or info.value.value == value
                    assert named, (value, str(info.value))
                    tried.add((schema.__name__, name))
                    break
    assert declared - tried == set()
    assert len(tried) > 60


EXPERIMENT_TASKS = {
    "demo": ("train", "certify", "smooth", "attack"),
    "reproduce_paper": ("train", "certify", "smooth", "attack"),
    "tabletop": ("train", "smooth", "attack"),
    "sweep": ("certify",),
    "reproduce_quick": ("train", "certify", "smooth", "attack"),
    "learning_curve": ("train",),
    "learning_curve_any": ("train",),
    "learning_curve_resnet18": ("train",),
    "side_by_side": ("train", "certify"),
}


def pick(jobs: list, every_job: bool) -> list:
    return jobs if every_job else [*jobs[:2], jobs[-1]]


@pytest.mark.parametrize("every_job", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_every_experiment_dry_runs_and_evaluates_only_models_the_experiments_train(every_job):
    """Each job of each experiment, with every task it is meant for, composes and validates;
    every model an evaluation job looks up is one that a train job of the experiments makes.
    The fast run takes each experiment's first, second and last job; ``slow`` takes all."""
    from mrcert.infra.identity import identify
    from mrcert.infra.resolver import train_key
    from mrcert.infra.tasks import TASKS
    from mrcert.reporting.experiment_cells import sweep_combos

    assert set(EXPERIMENT_TASKS) == {p.stem for p in (CONF_DIR / "experiment").glob("*.yaml")}
    trained, evaluated = set(), {}
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        jobs = [
            (experiment, task, combo)
            for experiment, tasks in EXPERIMENT_TASKS.items()
            for combo in pick(sweep_combos(experiment), every_job)
            for task in tasks
        ]
        for experiment, task, combo in jobs:
            cfg = compose("config", overrides=[f"experiment={experiment}", f"task={task}", *combo])
            validate(cfg)
            if task == "train":
                trained.add(identify(plain(cfg), TASKS["train"].identity).key)
            else:
                evaluated[train_key(cfg)] = f"experiment={experiment} task={task} {' '.join(combo)}"
    assert {k: v for k, v in evaluated.items() if k not in trained} == {}


@pytest.mark.parametrize(
    "override,key",
    [
        ("task.n=abc", "task.n"),
        ("motion.sigma=fast", "motion.sigma"),
        ("data.image.height=tall", "data.image.height"),
        ("train.amp=maybe", "train.amp"),
        ("task.n_samples=5", "task.n_samples"),
    ],
)
def test_a_bad_type_or_an_unknown_key_fails_at_composition(override, key):
    """The structured-config schemas (mrcert/infra/schema.py) reject these before any code runs."""
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException) as info:
        compose_cfg(["task=certify", override])
    assert key in str(info.value) + str(info.value.__cause__)


@pytest.mark.parametrize("override", ["+task.n_samples=5", "+model.weights=imagenet", "+data.image.gamma=2"])
def test_a_key_added_with_plus_that_no_schema_has_is_named(override):
    key = override[1:].split("=")[0]
    with pytest.raises(ConfigError, match=rf"config value {key}=.* not a key of this"):
        validate(compose_cfg(["task=certify", override]))


@pytest.mark.parametrize("override,near", [("+seeed=1", "did you mean seed?"), ("+foo=1", "its keys: task, data")])
def test_an_unknown_top_level_key_is_refused_naming_the_nearest(override, near):
    """A typo such as ``+seeed=1`` would otherwise run and record a separate result."""
    key = override[1:].split("=")[0]
    with pytest.raises(
        ConfigError, match=rf"config value {key}=1 is not allowed: not a key of mrcert's config"
    ) as info:
        validate(compose_cfg(["task=train", override]))
    assert near in str(info.value)


def test_an_unknown_top_level_key_leaves_no_run(tmp_path):
    proc = run_cli(["task=render", "data=testscene", "+seeed=1"], tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "did you mean seed?" in proc.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "mlflow.db").exists() and not list((tmp_path / "runs").glob("*/*"))


def test_table_links_follow_the_ui_port(monkeypatch):
    """``make ... PORT=5123`` exports the UI's address; the tables' links point there."""
    import subprocess

    shown = subprocess.run(
        ["make", "-s", "--eval", "show-ui-url:;@echo $$MRCERT_UI_URL", "show-ui-url", "PORT=5123"],
        cwd=CONF_DIR.parent, capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert shown.stdout.strip() == "http://127.0.0.1:5123"
    monkeypatch.setenv("MRCERT_UI_URL", shown.stdout.strip())
    assert compose_cfg(["task=tables"]).task.ui_url == "http://127.0.0.1:5123"


def test_the_defaults_order_is_read_from_the_root_config():
    """The order the check of later overrides relies on is the root config's, method and hydra included."""
    assert DEFAULTS_ORDER[:4] == ["task", "data", "profile", "train"] and DEFAULTS_ORDER[-1] == "experiment"
    assert DEFAULTS_ORDER.index("motion") < DEFAULTS_ORDER.index("method") < DEFAULTS_ORDER.index("model")


def test_every_generated_data_set_and_the_recipe_change_under_profile_quick():
    """profile=quick coarsens each generated data set and shortens the recipe through values that
    name every profile (``${per_profile:{...}}``): a generated data set without one would run the
    paper's settings under profile=quick without a word. Data read from files has nothing to coarsen."""
    from mrcert.data.synthetic import FAMILIES

    generated = [p.stem for p in (CONF_DIR / "data").glob("*.yaml") if OmegaConf.load(p).get("source") in FAMILIES]
    assert generated, "no generated data set found"
    for data in generated:
        quick, paper = (plain(compose_cfg([f"data={data}", f"profile={p}"])) for p in ("quick", "paper"))
        assert quick["data"] != paper["data"] and quick["train"] != paper["train"], data
        assert quick["profile"]["name"] == "quick" and paper["profile"]["name"] == "paper"


@pytest.mark.parametrize("values", [{"quick": 1}, {"paper": 1, "quick": 2, "fast": 3}, 5])
def test_a_value_that_depends_on_the_profile_names_every_profile(values):
    from mrcert.infra.config import per_profile

    root = OmegaConf.create({"profile": {"name": "quick"}})
    with pytest.raises(ConfigError, match="a value for each profile: paper, quick"):
        per_profile(values, _root_=root)
    assert per_profile({"paper": 1, "quick": 2}, _root_=root) == 2


def test_no_config_is_chosen_by_a_name_made_of_other_choices():
    """An experiment says what it changes in its own file: no defaults entry of the root config
    interpolates other choices into a file name (an overlay that, when missing, silently falls
    back to the defaults)."""
    entries = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "config.yaml").defaults)
    assert not [e for e in entries if "${" in str(e)]


EVALUATIONS = ("certify", "smooth", "attack")


@pytest.mark.parametrize("experiment", options("experiment"))
def test_an_experiment_s_per_task_settings_reach_that_task_alone(experiment):
    """Every per-task setting an experiment gives (demo's every 12th image, the tabletop's vote over
    10 samples, the reproduction's every 2nd attacked image) is the composed value of that task,
    under every profile; the other evaluation tasks keep their own defaults; the command line wins."""
    for profile in options("profile"):
        settings = plain(compose_cfg([f"experiment={experiment}", f"profile={profile}"]))["per_task"]
        defaults = {t: plain(compose_cfg([f"task={t}", f"profile={profile}"]))["task"] for t in EVALUATIONS}
        for task in EVALUATIONS:
            composed = plain(compose_cfg([f"experiment={experiment}", f"profile={profile}", f"task={task}"]))["task"]
            wanted = defaults[task] | settings.get(task, {})
            assert {k: composed[k] for k in wanted} == wanted, (experiment, profile, task)
        for task, values in settings.items():
            given = {k: "vote" if k == "decision" else 3 for k in values}
            composed = plain(
                compose_cfg([f"experiment={experiment}", f"task={task}", *(f"task.{k}={v}" for k, v in given.items())])
            )
            assert {k: composed["task"][k] for k in given} == given, (experiment, task)


def test_the_shipped_experiments_give_the_settings_their_tables_rest_on():
    """The values the evidence page's cells were computed with (their run keys hold them)."""
    task = {
        (e, t): plain(compose_cfg([f"experiment={e}", f"task={t}"]))["task"]
        for e, t in [
            ("demo", "certify"),
            ("demo", "attack"),
            ("reproduce_quick", "attack"),
            ("reproduce_quick", "certify"),
            ("tabletop", "smooth"),
            ("side_by_side", "certify"),
        ]
    }
    assert task["demo", "certify"]["skip"] == task["demo", "attack"]["skip"] == 12
    assert (task["reproduce_quick", "attack"]["skip"], task["reproduce_quick", "certify"]["skip"]) == (2, 1)
    assert (
        task["reproduce_quick", "certify"]["n"],
        task["tabletop", "smooth"]["n"],
        task["tabletop", "smooth"]["decision"],
    ) == (1000, 10, "vote")
    assert task["side_by_side", "certify"]["skip"] == 5


@pytest.mark.parametrize(
    "override,key,allowed",
    [
        ("+per_task.atack.skip=2", "per_task.atack", "settings of one of the tasks certify, smooth, attack, export"),
        ("+per_task.train.skip=2", "per_task.train", "settings of one of the tasks certify, smooth, attack, export"),
        (
            "+per_task.attack.alpha=0.05",
            "per_task.attack.alpha",
            "one of the per-task settings n, decision, skip, sequential",
        ),
        ("+per_task.attack=2", "per_task.attack", "a mapping of some of n, decision, skip, sequential"),
    ],
)
def test_a_per_task_setting_no_task_reads_is_refused_whatever_the_task(override, key, allowed):
    """A mistyped task or key under ``per_task`` would otherwise be silently ignored: refused by
    validation, naming it, even when the task run is another one."""
    with pytest.raises(ConfigError) as err:
        validate(compose_cfg(["task=train", override]))
    assert (err.value.key, err.value.allowed) == (key, allowed)
