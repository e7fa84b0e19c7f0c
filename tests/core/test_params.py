"""One parameter vocabulary (issue 24): QuickMatchParams in quickmatch / QuickMatch / DQMConfig, and the
command-line options generated from the dataclass fields."""
import argparse
import dataclasses

import numpy as np
import pytest

import dqm
from dqm import synthetic
from dqm.commands import runtime_options
from dqm.commands.param_options import add_quickmatch_params
from dqm.core import clustering
from dqm.core.params import (
    DEFAULT_KERNEL,
    DEFAULT_RATIO_DENSITY,
    DEFAULT_RHO,
    FINITE_KERNEL,
    KERNELS,
    PARENT_MODES,
    QuickMatchParams,
)
from dqm.distributed.config import SHARED_PARAMS, DQMConfig
from dqm.validation import InputError


@pytest.fixture(scope="module")
def scene():
    ds = synthetic.sift_like(n_images=4, n_points=60, clutter_per_image=20, noise=0.3, seed=3)
    return ds.descriptors, ds.image_ids


def test_clustering_reexports_the_vocabulary():
    assert (clustering.KERNELS, clustering.PARENT_MODES) == (KERNELS, PARENT_MODES)
    assert (clustering.DEFAULT_RHO, clustering.DEFAULT_RATIO_DENSITY) == (DEFAULT_RHO, DEFAULT_RATIO_DENSITY)
    assert dqm.core.DEFAULT_RHO is DEFAULT_RHO


def test_quickmatch_takes_params_or_keywords_not_both(scene):
    X, ids = scene
    p = QuickMatchParams(rho=0.8, kernel="quadratic", parent="other-image")
    by_params = dqm.quickmatch(X, ids, params=p)
    by_keywords = dqm.quickmatch(X, ids, rho=0.8, kernel="quadratic", parent="other-image")
    np.testing.assert_array_equal(by_params.labels, by_keywords.labels)
    assert by_params.params == by_keywords.params == p
    assert dqm.quickmatch(X, ids).params == QuickMatchParams()  # the defaults, unchanged
    # the exactness contract: a result's params reproduce its labels
    np.testing.assert_array_equal(dqm.quickmatch(X, ids, **by_params.params.as_kwargs()).labels, by_params.labels)
    with pytest.raises(InputError, match="not both.*rho="):
        dqm.quickmatch(X, ids, params=p, rho=0.8)
    with pytest.raises(InputError, match="params must be a QuickMatchParams"):
        dqm.quickmatch(X, ids, params={"rho": 0.8})
    with pytest.raises(InputError, match="kernel must be one of"):
        dqm.quickmatch(X, ids, params=p.but(kernel="box"))
    with pytest.raises(InputError, match="rho must be a positive"):
        dqm.quickmatch(X, ids, rho=-1)


def test_result_params_are_python_floats(scene):
    X, ids = scene
    r = dqm.quickmatch(X, ids, rho=np.float32(0.75), ratio_density=1)
    assert type(r.rho) is float and type(r.params.ratio_density) is float and r.params.rho == 0.75


def test_estimator_params(scene):
    X, ids = scene
    qm = dqm.QuickMatch(rho=0.7, kernel="quadratic")
    assert qm.params == QuickMatchParams(rho=0.7, kernel="quadratic")
    assert set(QuickMatchParams.names()) <= set(qm.get_params())
    qm.fit(X, ids)
    assert qm.params_ == qm.result_.params == QuickMatchParams(rho=0.7, kernel="quadratic")
    np.testing.assert_array_equal(qm.labels_, dqm.quickmatch(X, ids, rho=0.7, kernel="quadratic").labels)
    assert qm.set_params(rho=0.5).params.rho == 0.5 and qm.params_.rho == 0.7  # fitted params stay


def test_config_shares_the_vocabulary():
    cfg = DQMConfig(agents=3, rho=0.8)
    assert cfg.kernel == FINITE_KERNEL and DQMConfig(agents=2).rho == DEFAULT_RHO
    assert cfg.params == QuickMatchParams(rho=0.8, kernel=FINITE_KERNEL, parent="any")
    with pytest.raises(InputError, match="a balanced-mode distributed job needs the finite kernel"):
        DQMConfig(agents=2, mode="balanced", kernel=DEFAULT_KERNEL).validated()
    for mode in ("lean", "paper"):  # approximate modes: either kernel
        assert DQMConfig(agents=2, mode=mode, kernel=DEFAULT_KERNEL).validated().kernel == DEFAULT_KERNEL
    with pytest.raises(InputError, match="rho must be a positive"):
        DQMConfig(agents=2, rho=0).validated()


#: the shared parameters in the order the wire has always carried them (params_text is compared byte for byte
#: between processes, and its hash travels in the start message)
WIRE_ORDER = ("agents", "mode", "partition", "kernel", "rho", "halo", "samples_per_agent", "seed_norm",
              "cell_weights", "ghost_rule", "sketch_dims", "balance_rounds",
              "engine", "copy_budget")  # added last (issue 62): a process without them is refused
              # ("engine differs: (absent)")

CONFIGS = [
    DQMConfig(agents=1),
    DQMConfig(agents=4, seed=7, job="j-1"),
    DQMConfig(agents=8, seed=3, partition="seeded", mode="lean", rho=0.75, halo=1.5, samples_per_agent=16,
              seed_norm=1.0, job="-dash", cell_weights=False, ghost_rule="two-way", sketch_dims=0,
              balance_rounds=0),
    DQMConfig(agents=5, mode="paper", rho=0.1 + 0.2, halo=2.0, cell_weights=True, sketch_dims=7, balance_rounds=3),
]


@pytest.mark.parametrize("cfg", CONFIGS)
def test_params_text_is_byte_identical_to_the_old_formula(cfg):
    assert SHARED_PARAMS == WIRE_ORDER
    assert cfg.params_text() == ";".join(f"{k}={getattr(cfg, k)!r}" for k in WIRE_ORDER)


def test_every_config_field_has_metadata():
    flags = set()
    for f in dataclasses.fields(DQMConfig):
        assert f.metadata["help"] and f.metadata["flag"].startswith("--")
        assert (f.metadata["shared"] is not None) == (f.name in WIRE_ORDER)
        flags.add(f.metadata["flag"])
    assert len(flags) == len(dataclasses.fields(DQMConfig))


def _algorithm_parser():
    p = argparse.ArgumentParser(exit_on_error=False)
    runtime_options.add_algorithm(p)
    return p


@pytest.mark.parametrize("cfg", CONFIGS)
def test_config_args_round_trip(cfg):
    args = _algorithm_parser().parse_args(runtime_options.config_args(cfg))
    assert runtime_options.config_from(args, cfg.agents, cfg.seed) == cfg
    assert runtime_options.config_from(args, cfg.agents, cfg.seed).params_text() == cfg.params_text()


@pytest.mark.parametrize("cfg", CONFIGS[1:3])
def test_config_args_start_the_real_commands(cfg):
    """As the launcher uses them: an agent process (no --seed: the coordinator broadcasts it) and the coordinator."""
    from dqm.cli import build_parser

    parser = build_parser()
    agent = parser.parse_args(["agent", "--id", "0", "--agents", str(cfg.agents), "--connect", "tcp/127.0.0.1:7447",
                               *runtime_options.config_args(cfg), "f.npz"])
    assert runtime_options.config_from(agent, agent.agents) == cfg.but(seed=0)
    coordinator = parser.parse_args(["coordinator", "--agents", str(cfg.agents), "--seed", str(cfg.seed),
                                     "--connect", "tcp/127.0.0.1:7447", *runtime_options.config_args(cfg)])
    assert runtime_options.config_from(coordinator, coordinator.agents, coordinator.seed) == cfg


def test_algorithm_options_keep_their_flags_and_defaults():
    p = _algorithm_parser()
    defaults = runtime_options.config_from(p.parse_args([]), agents=2, seed=1)
    assert defaults == DQMConfig(agents=2, seed=1)
    a = p.parse_args(["--samples", "9", "--no-cell-weights", "--seed-norm", "2", "--kernel", "quadratic",
                      "--mode", "lean", "--partition", "seeded", "--halo", "3", "--ghost-rule", "two-way",
                      "--sketch-dims", "5", "--balance-rounds", "4", "--job", "x", "--rho", "0.5"])
    cfg = runtime_options.config_from(a, agents=2)
    assert (cfg.samples_per_agent, cfg.cell_weights, cfg.seed_norm, cfg.halo, cfg.rho) == (9, False, 2.0, 3.0, 0.5)
    assert (cfg.mode, cfg.partition, cfg.ghost_rule, cfg.sketch_dims, cfg.balance_rounds, cfg.job) == \
        ("lean", "seeded", "two-way", 5, 4, "x")
    assert runtime_options.config_from(p.parse_args(["--samples-per-agent", "3", "--cell-weights"]),
                                       2).but(seed=1) == DQMConfig(agents=2, samples_per_agent=3, cell_weights=True)
    with pytest.raises(argparse.ArgumentError):
        p.parse_args(["--mode", "fast"])


def test_quickmatch_options_come_from_the_fields():
    p = argparse.ArgumentParser()
    add_quickmatch_params(p, notes={"rho": " (note)"})
    args = p.parse_args([])
    assert QuickMatchParams(**{k: getattr(args, k) for k in QuickMatchParams.names()}) == QuickMatchParams()
    args = p.parse_args(["--rho", "0.5", "--kernel", "quadratic", "--parent", "other-image",
                         "--ratio-density", "0.5"])
    assert (args.rho, args.kernel, args.parent, args.ratio_density) == (0.5, "quadratic", "other-image", 0.5)
    rho = next(a for a in p._actions if a.dest == "rho")
    assert rho.help.endswith(" (note)") and rho.help.startswith("merge ratio")
    q = argparse.ArgumentParser()
    add_quickmatch_params(q, ("kernel",), kernel_default=FINITE_KERNEL)
    assert q.parse_args([]).kernel == FINITE_KERNEL and not hasattr(q.parse_args([]), "rho")


def test_commands_defaults_stay():
    from dqm.cli import build_parser

    parser = build_parser()
    m = parser.parse_args(["match", "x.npz", "--out", "o.npz"])
    assert (m.rho, m.kernel, m.parent, m.ratio_density) == (DEFAULT_RHO, "gaussian", "any", DEFAULT_RATIO_DENSITY)
    assert parser.parse_args(["demo"]).rho == DEFAULT_RHO
    assert parser.parse_args(["stream", "--connect", "tcp/127.0.0.1:7447"]).rho == DEFAULT_RHO
    r = parser.parse_args(["run"])
    assert runtime_options.config_from(r, r.agents, r.seed) == DQMConfig(agents=r.agents, seed=r.seed)
