"""``roverswarm export``: ONNX models of every actor kind act as the JAX policies do, fed by the
NumPy observation reference, in episodes of the JAX environment; the docs' snippet runs with
numpy and onnxruntime alone; bad exports end with one line and exit code 2."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import subprocess
import sys
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import onnxruntime as ort
import pytest
from configs import SMALL_ENTITY  # tests/configs.py

from roverswarm import export_numpy
from roverswarm.config import TrainConfig, config_to_json, validate, with_options
from roverswarm.env import get_scenario
from roverswarm.env.entities import EntityView, nearest_entities, observe_entities
from roverswarm.env.mars import NEVER, EnvState, failed_rovers, observe, reset, step_env
from roverswarm.errors import UserError
from roverswarm.export import SHIELD, SNIPPET, env_constants, export_run, random_states, trained_sizes
from roverswarm.learners import learner_family
from roverswarm.learners.base import Runner
from roverswarm.presets import ANYSIZE, IPPO, MAPPO, SWARM
from roverswarm.runs import CHECKPOINT, CONFIG, Run
from roverswarm.steering import shield_actions
from roverswarm.storage import atomic_write, save_checkpoint

DOCS = Path(__file__).parent.parent / "docs" / "export.md"
EPISODES, SEED = 40, 1  # 40 episodes of 25 steps: 1,000 recorded swarm observations; seed 1 of 2


def tiny(base: TrainConfig, options: dict, scenario: str) -> TrainConfig:
    options = with_options(base, options)
    return dataclasses.replace(options, scenario=scenario, episodes=100, log_every=100, num_envs=4, seeds=2)


KINDS = {  # every actor kind: per-rover and shared off-policy actors, the on-policy mlp, entity and nearest
    "maddpg": tiny(TrainConfig(), {"hidden": (16, 16), "layer_norm": True, "normalize_obs": True}, "paper-2"),
    "ddpg-shared": tiny(SWARM, {"algo": "ddpg", "hidden": (16,), "normalize_obs": True}, "paper-3"),
    "mappo": tiny(MAPPO, {"hidden": (16,)}, "paper-3"),
    "ippo": tiny(IPPO, {"hidden": (16, 16), "activation": "relu"}, "paper-2"),
    "entity": tiny(ANYSIZE, {**SMALL_ENTITY, "entity_layers": 2, "hidden": (16,)}, "paper-2..4"),
    "nearest": tiny(ANYSIZE, {"hidden": (16,), "entity_nearest": 2}, "paper-2..4"),
    "nearest-shield": tiny(ANYSIZE, {"hidden": (16,), "entity_nearest": 2, "shield": True}, "paper-2..4"),
    "maddpg-nearest": tiny(
        SWARM, {"network": "nearest", "entity_nearest": 2, "critic_neighbors": 1, "layer_norm": True}, "paper-3"
    ),
}
EPISODE_SCENARIO = {  # a size never trained on
    "entity": "paper-5",
    "nearest": "paper-5",
    "nearest-shield": "paper-5",
    "maddpg-nearest": "paper-5",
}


def make_run(config: TrainConfig, folder: Path, episodes_done: int | None = None) -> Path:
    """A run folder as training leaves it, with random actor weights (and a random observation
    normaliser): parity needs no learning. The checkpoint holds ``episodes_done`` episodes
    (default: all of them, a finished run)."""
    params = validate(config)
    family = learner_family(config.learner.algo)
    shapes = jax.eval_shape(lambda: family.learners(family.configure(config, params), params))
    rng = np.random.default_rng(zlib.crc32(folder.name.encode()))
    learner = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), shapes)

    def draw(path, s):  # kernels at the scale of Flax's default initialisation (LeCun normal)
        if len(s.shape) >= 3 and s.shape[-2] > 1:  # a kernel [S, ..., in, out]
            return (rng.standard_normal(s.shape) / np.sqrt(s.shape[-2])).astype(np.float32)
        scale = jax.tree_util.keystr(path).endswith("['scale']")  # a LayerNorm's scale
        return (scale + 0.2 * rng.standard_normal(s.shape)).astype(np.float32)

    learner = learner.replace(actor=jax.tree_util.tree_map_with_path(draw, shapes.actor))
    if getattr(learner, "obs_norm", None) is not None:
        shape = learner.obs_norm.mean.shape
        learner = learner.replace(
            obs_norm=learner.obs_norm.replace(
                mean=0.3 * rng.standard_normal(shape, np.float32), var=rng.uniform(0.2, 2.0, shape).astype(np.float32)
            )
        )
    done = config.episodes if episodes_done is None else episodes_done
    runner = Runner(learner, None, np.zeros((config.seeds, 2), np.uint32), np.int32(done), np.int32(0))
    folder.mkdir(parents=True)
    atomic_write(folder / CONFIG, lambda f: f.write(config_to_json(config)))
    save_checkpoint(folder / CHECKPOINT, runner, replay=False, config_json=config_to_json(config))
    return folder


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """kind -> (run folder, export folder) of seed 1 of every kind."""
    root = tmp_path_factory.mktemp("export")
    folders = {}
    for kind, config in KINDS.items():
        run = make_run(config, root / "runs" / kind)
        result = export_run(run, root / "exports" / kind, seed=SEED)
        assert result.difference < 1e-5  # the export's own check against JAX
        folders[kind] = (run, root / "exports" / kind)
    return folders


# ----------------------------------------------------------------------------- the NumPy observations


@pytest.mark.parametrize("n", [3, 6])
def test_the_numpy_observations_equal_the_jax_ones(n):
    """Random states at two swarm sizes, some rovers failed, some POIs observed: the flat view
    in both orders, the entity view, and its cut to 2 and to 4 of each type (4: more slots
    than other rovers at N = 3, padded and masked), and to 2 with the open POIs first; the
    entity view with the greedy matching as its claim, whole and cut to 2 with the matched POI
    first."""
    params, count = get_scenario(f"paper-{n}"), 8
    states = random_states(params, count, seed=n)
    failing = np.random.default_rng(n).random((count, n)) < 0.4
    states = states.replace(time=np.full(count, 10, np.int32), fail_step=np.where(failing, 5, NEVER).astype(np.int32))

    @jax.jit
    def views(states):
        flat = [jax.vmap(observe, in_axes=(0, None))(states, params.replace(nearest_first=f)) for f in (False, True)]
        every = jax.vmap(observe_entities, in_axes=(0, None))(states, params)
        cuts = [nearest_entities(every, params, 2), nearest_entities(every, params, 4)]
        matched = jax.vmap(observe_entities, in_axes=(0, None, None))(states, params, True)
        free_first = [nearest_entities(every, params, 2, free_first=True), matched]
        return flat, [every, *cuts, *free_first, nearest_entities(matched, params, 2, free_first=True)]

    flat, entity = jax.device_get(views(states))
    for e in range(count):
        s = jax.tree.map(lambda x, e=e: x[e], states)
        args = (s.rover_pos, s.rover_vel, s.poi_pos, s.trap_pos)
        for nearest_first, expected in zip((False, True), flat, strict=True):
            np.testing.assert_allclose(export_numpy.observe_flat(*args, nearest_first), expected[e], atol=1e-6)
        every = export_numpy.observe_entities(*args, s.observed, failing[e], 0.15, 0.1, 0.1)
        matched = export_numpy.observe_entities(*args, s.observed, failing[e], 0.15, 0.1, 0.1, matched=True)
        ours = [every] + [
            export_numpy.nearest_entities(*every, k, (n - 1, n, n), f) for k, f in ((2, 0), (4, 0), (2, 1))
        ]
        ours += [matched, export_numpy.nearest_entities(*matched, 2, (n - 1, n, n), True)]
        for got, want in zip(ours, entity, strict=True):
            for a, b in zip(got, (want.own[e], want.tokens[e], want.mask[e]), strict=True):
                np.testing.assert_allclose(a, b, atol=1e-6)
    assert failing.any() and (~failing).any()


@pytest.mark.parametrize("n", [3, 6])
def test_the_numpy_safety_layer_equals_the_jax_one(n):
    """The exported layer (``observation.py``'s ``shield_actions``) against the package's on
    random states, some rovers failed, actions beyond the clip: the same actions, and many of
    the rovers turned (30% at N = 3, 54% at 6: the comparison is of its turns, not its clip)."""
    params, count = get_scenario(f"paper-{n}"), 64
    states = random_states(params, count, seed=10 + n)
    failing = np.random.default_rng(n).random((count, n)) < 0.3
    states = states.replace(time=np.full(count, 10, np.int32), fail_step=np.where(failing, 5, NEVER).astype(np.int32))
    actions = 1.5 * np.random.default_rng(20 + n).standard_normal((count, n, 2)).astype(np.float32)
    want = np.asarray(jax.jit(jax.vmap(shield_actions, in_axes=(0, 0, None)))(states, actions, params))
    meta = {"env": env_constants(params), "shield": SHIELD}
    got = np.stack(
        [
            export_numpy.shield_actions(
                meta, actions[e], states.rover_pos[e], states.rover_vel[e], states.trap_pos[e], failing[e]
            )
            for e in range(count)
        ]
    )
    np.testing.assert_allclose(got, want, atol=1e-5)
    turned = np.abs(got - np.clip(actions, -1, 1)).max(axis=-1) > 1e-3
    assert turned.mean() > 0.2, turned.mean()
    # a failed rover is kept at the smaller margin: with the working rovers' margin the layer differs
    wider = {"env": meta["env"], "shield": dict(SHIELD, failed_margin=SHIELD["keep_out_margin"])}
    other = [
        export_numpy.shield_actions(wider, actions[e], states.rover_pos[e], states.rover_vel[e], states.trap_pos[e], f)
        for e, f in enumerate(failing)
    ]
    assert np.abs(np.stack(other) - want).max() > 1e-3


def test_the_numpy_safety_layer_refuses_an_export_without_it_and_misshapen_actions():
    params = get_scenario("paper-3")
    state = jax.tree.map(lambda x: x[0], random_states(params, 1))
    swarm = (state.rover_pos, state.rover_vel, state.trap_pos)
    plain = {"env": env_constants(params), "shield": None}
    with pytest.raises(ValueError, match="holds no safety layer"):
        export_numpy.shield_actions(plain, np.zeros((3, 2)), *swarm)
    with pytest.raises(ValueError, match=r"actions must be \[N, 2\] or \[1, N, 2\] for 3 rovers, got shape \(2, 3\)"):
        export_numpy.shield_actions(dict(plain, shield=SHIELD), np.zeros((2, 3)), *swarm)


# ----------------------------------------------------------------------------- ONNX against JAX


STEP = jax.jit(jax.vmap(step_env, in_axes=(0, 0, None)))


def episodes(run: Path, export: Path, params) -> dict:
    """40 episodes from the same layouts, stepped by the JAX environment: one driven by the JAX
    policy, one by the ONNX model fed from the NumPy observations (what a user without JAX
    runs). Returns both episode rewards, final positions, and the ONNX run's recorded inputs
    and actions."""
    meta = json.loads((export / "policy.json").read_text())
    session = ort.InferenceSession(str(export / "policy.onnx"))
    policy = Run(run).policy(SEED)
    _, start = jax.vmap(reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(5), EPISODES), params)
    jax_act = jax.jit(jax.vmap(lambda s: policy.act(None, observe(s, params), s, None, policy.weights, params)))
    out = {"inputs": [], "actions": []}
    for driver in ("jax", "onnx"):
        state, total = start, np.zeros(EPISODES)
        for _ in range(params.max_steps):
            if driver == "jax":
                actions = jax_act(state)
            else:
                s = jax.device_get(state)
                failed = np.asarray(jax.vmap(failed_rovers)(state))
                views = [
                    export_numpy.model_inputs(
                        meta,
                        s.rover_pos[e],
                        s.rover_vel[e],
                        s.poi_pos[e],
                        s.trap_pos[e],
                        s.observed[e],
                        failed[e],
                    )
                    for e in range(EPISODES)
                ]
                inputs = {name: np.concatenate([v[name] for v in views]) for name in views[0]}
                (actions,) = session.run(["actions"], inputs)
                out["inputs"].append(inputs)
                out["actions"].append(actions)
                if meta["shield"]:  # exported with the safety layer: its NumPy copy after the model
                    actions = np.stack(
                        [
                            export_numpy.shield_actions(
                                meta, a, s.rover_pos[e], s.rover_vel[e], s.trap_pos[e], failed[e]
                            )
                            for e, a in enumerate(actions)
                        ]
                    )
            _, state, rewards, *_ = STEP(state, jnp.asarray(actions), params)
            total += np.asarray(rewards).sum(axis=-1)
        out[driver] = (total, np.asarray(state.rover_pos))
    return out


def jax_actions(run: Path, inputs: dict) -> np.ndarray:
    """The JAX policy's actions on recorded model inputs (flat obs, or an entity view)."""
    config = Run(run).config
    family = learner_family(config.learner.algo)
    view = inputs["obs"] if "obs" in inputs else EntityView(inputs["own"], inputs["tokens"], inputs["mask"])
    weights = jax.tree.map(lambda x: x[SEED], family.weights(Run(run).learner))
    return np.asarray(jax.jit(family.act, static_argnums=0)(family.acting(config), weights, view, None))


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_onnx_model_acts_as_the_jax_policy(exported, kind):
    run, export = exported[kind]
    params = get_scenario(EPISODE_SCENARIO[kind]) if kind in EPISODE_SCENARIO else Run(run).params
    out = episodes(run, export, params)
    recorded = {name: np.concatenate([i[name] for i in out["inputs"]]) for name in out["inputs"][0]}
    onnx_actions = np.concatenate(out["actions"])
    assert len(onnx_actions) == EPISODES * params.max_steps == 1000
    difference = np.abs(onnx_actions - jax_actions(run, recorded)).max()
    assert difference <= 1e-5, difference
    assert np.abs(onnx_actions).mean() > 0.1  # the actions are not all near zero
    (jax_reward, jax_pos), (onnx_reward, onnx_pos) = out["jax"], out["onnx"]
    np.testing.assert_allclose(onnx_reward, jax_reward, rtol=1e-5)
    np.testing.assert_allclose(onnx_pos, jax_pos, atol=1e-4)


# ----------------------------------------------------------------------------- the docs' snippet


def docs_snippet() -> str:
    """The Python block of docs/export.md that follows 'Run it'."""
    text = DOCS.read_text()
    return re.search(r"```python\n(import json\n.*?)```", text, re.DOTALL)[1]


def test_the_docs_snippet_is_the_exports(exported):
    assert docs_snippet() == SNIPPET
    for _, export in exported.values():
        assert SNIPPET in (export / "README.md").read_text()


@pytest.mark.parametrize("kind", ["ddpg-shared", "entity", "nearest-shield"])
def test_the_docs_snippet_runs_with_numpy_and_onnxruntime_alone(exported, kind, tmp_path):
    """Behind the layer too (a run trained with it, the snippet's layout crowded into a tenth of
    the map so that the layer turns a rover): the snippet's actions are the JAX policy's turned
    by the JAX layer."""
    run, export = exported[kind]
    snippet = docs_snippet()
    shielded = Run(run).config.learner.shield
    if shielded:
        assert snippet.count("rng.uniform(-1, 1,") == 3
        snippet = snippet.replace("rng.uniform(-1, 1,", "rng.uniform(-0.3, 0.3,")
    probe = (
        snippet
        + "\nimport sys\nnp.savez(sys.argv[1], actions=actions, rover_pos=rover_pos, rover_vel=rover_vel, "
        + "poi_pos=poi_pos, trap_pos=trap_pos, **inputs)\n"
        + "print(sorted({m.split('.')[0] for m in sys.modules} & {'jax', 'jaxlib', 'flax', 'roverswarm'}))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe, str(tmp_path / "out.npz")],
        cwd=export,
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"  # no JAX, no roverswarm in that process
    saved = dict(np.load(tmp_path / "out.npz"))
    actions = saved.pop("actions")
    swarm = {name: saved.pop(name).astype(np.float32) for name in ("rover_pos", "rover_vel", "poi_pos", "trap_pos")}
    want = jax_actions(run, saved)
    if shielded:
        n, p = len(swarm["rover_pos"]), len(swarm["poi_pos"])
        state = EnvState(**swarm, observed=np.zeros(p, bool), time=np.int32(0), fail_step=np.full(n, NEVER, np.int32))
        model = want
        want = np.asarray(shield_actions(state, want[0], trained_sizes(Run(run))[0]))[None]
        assert np.abs(want - np.clip(model, -1, 1)).max() > 1e-2  # the layer turned a rover
    np.testing.assert_allclose(actions, want, atol=1e-5)


# ----------------------------------------------------------------------------- the command


def test_the_command_exports_the_seed_it_is_given(exported, tmp_path, capsys):
    from roverswarm.cli import main

    run, export = exported["mappo"]
    assert main(["export", str(run), "--out", str(tmp_path / "seed0")]) == 0
    assert "ONNX and JAX actions differ by at most" in " ".join(capsys.readouterr().out.split())
    meta = json.loads((tmp_path / "seed0" / "policy.json").read_text())
    assert (meta["seed"], meta["algo"], meta["view"]["nearest_first"]) == (0, "mappo", True)
    assert meta["inputs"] == {"obs": ["batch", 3, 20]} and meta["outputs"] == {"actions": ["batch", 3, 2]}
    obs = {"obs": np.random.default_rng(0).normal(size=(4, 3, 20)).astype(np.float32)}
    seed0, seed1 = (
        ort.InferenceSession(str(f / "policy.onnx")).run(None, obs)[0] for f in (tmp_path / "seed0", export)
    )
    assert np.abs(seed0 - seed1).max() > 0.1  # another seed's networks


def test_export_shield_adds_the_layer_to_a_run_trained_without_it(exported, tmp_path, capsys):
    """``export --shield``: policy.json holds the layer's constants (None without it, and for a
    run trained behind it it is always there), the README says to apply it."""
    from roverswarm.cli import main

    run, plain = exported["mappo"]
    assert main(["export", str(run), "--out", str(tmp_path / "shielded"), "--shield"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "with the safety layer" in out and "(both behind the safety layer)" in out
    assert float(re.search(r"differ by at most (\S+) on", out)[1]) < 1e-5
    meta = json.loads((tmp_path / "shielded" / "policy.json").read_text())
    assert meta["shield"] == dict(SHIELD, trained_behind=False)
    assert "apply `shield_actions`" in (tmp_path / "shielded" / "README.md").read_text()
    assert "trained without it (`export --shield`)" in (tmp_path / "shielded" / "README.md").read_text()
    assert json.loads((plain / "policy.json").read_text())["shield"] is None
    assert "shield_actions`" not in (plain / "README.md").read_text()
    trained = json.loads((exported["nearest-shield"][1] / "policy.json").read_text())
    assert trained["shield"] == dict(SHIELD, trained_behind=True)


def test_refusals_are_one_line_and_exit_code_2(exported, tmp_path, capsys):
    from roverswarm.cli import main

    run, _ = exported["ippo"]
    ensemble = make_run(tiny(TrainConfig(), {"hidden": (8,), "ensemble": 2}, "paper-2"), tmp_path / "ensemble")
    unfinished = make_run(KINDS["ippo"], tmp_path / "unfinished", episodes_done=0)
    cases = [
        ([str(tmp_path)], "holds no trained run"),
        ([str(unfinished)], "is not a finished run: its checkpoint holds 0 of 100 episodes"),
        ([str(run), "--seed", "2"], r"--seed must be in \[0, 2\)"),
        ([str(ensemble)], "is a policy ensemble"),
    ]
    for args, message in cases:
        assert main(["export", *args, "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and re.search(message, err[0]), err
        assert not (tmp_path / "out").exists()
    # into the run's own folder: the run's files stay its own (as `mission run --out RUN`)
    before = sorted(p.name for p in Path(run).iterdir())
    assert main(["export", str(run), "--out", str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds a training run" in err[0], err
    assert sorted(p.name for p in Path(run).iterdir()) == before


def test_an_export_does_not_replace_files_of_a_folder_that_holds_no_export(exported, tmp_path, capsys):
    """`export --out .` in a project would have replaced its README.md; an earlier export is
    replaced (the next test), a folder holding none of the export's files is written to."""
    from roverswarm.cli import main

    (tmp_path / "README.md").write_text("my project\n")
    assert main(["export", str(exported["ippo"][0]), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds README.md and no earlier roverswarm export" in err[0], err
    assert (tmp_path / "README.md").read_text() == "my project\n" and not (tmp_path / "policy.onnx").exists()


def test_an_export_that_cannot_write_every_file_changes_none(exported, tmp_path, capsys):
    """Each file was renamed in place as it was written: a README.md that could not be written
    left the other three files of another run's export beside the old README. Now every file
    is written first and renamed only once all are: the folder keeps the first export whole."""
    from roverswarm.cli import main

    out = tmp_path / "out"
    shutil.copytree(exported["mappo"][1], out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    (out / "README.md").unlink()
    (out / "README.md").mkdir()  # the one file that cannot be written
    assert main(["export", str(exported["ippo"][0]), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"cannot write '{out / 'README.md'}'" in err and "no file was changed" in err, err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == {
        name: data for name, data in before.items() if name != "README.md"
    }
    assert not list(out.glob("*.tmp"))


def test_a_run_its_budget_ended_is_finished_and_exports(tmp_path):
    """A run whose --budget-minutes ended it before its episodes (which `train --resume` will
    not continue) exports, as a sweep counts it finished; policy.json gives the episodes it
    trained. One stopped before its budget is spent is still refused with `train --resume`."""
    from roverswarm.runs import METRICS, write_csv

    config = dataclasses.replace(KINDS["ippo"], episodes=200, budget_minutes=0.001)
    for name, seconds in (("budget", 1.0), ("interrupted", 0.01)):  # 0.001 minutes: 0.06 seconds
        run = make_run(config, tmp_path / name, episodes_done=100)
        write_csv(run / METRICS, [{"seed": s, "episodes": 100, "wall_seconds": seconds} for s in range(config.seeds)])
    result = export_run(tmp_path / "budget", tmp_path / "out", seed=SEED)
    assert result.difference < 1e-5 and result.meta["trained_for"]["episodes"] == 100
    with pytest.raises(UserError, match=r"holds 100 of 200 episodes; finish it with `roverswarm train --resume"):
        export_run(tmp_path / "interrupted", tmp_path / "out2")
