"""``roverswarm export``: one seed's trained actor as an ONNX model that runs without JAX.

The export folder holds:

- ``policy.onnx``: the deterministic actor (no critic, no exploration noise), the
  observation normaliser of ``--normalize-obs`` inside it; inputs in the view the run was
  trained on (:mod:`roverswarm.export_onnx` writes the graph);
- ``policy.json``: what the inputs and outputs mean (the view, its layout and order, shapes,
  what the run was trained for, the environment's constants, the safety layer's constants
  under ``shield`` or null);
- ``observation.py``: the observation functions in NumPy alone (:mod:`roverswarm.export_numpy`),
  to feed the model from a swarm's state, and the safety layer in NumPy, which a run trained
  behind it (``train --shield``) or an ``export --shield`` applies to the model's actions;
- ``README.md``: how to run it with ``onnxruntime`` and NumPy (:data:`SNIPPET`).

Needs the ``export`` extra (``pip install -e ".[export]"``: ``onnx`` and ``onnxruntime``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
import tyro

from roverswarm import export_numpy
from roverswarm.algos.normalize import std
from roverswarm.config import TrainConfig
from roverswarm.env.mars import NEVER, EnvParams, EnvState, failed_rovers, observation_size, observe
from roverswarm.env.scenarios import get_scenario, range_sizes
from roverswarm.errors import UserError, require
from roverswarm.learners import learner_family, offpolicy
from roverswarm.runs import (
    CHECKPOINT,
    Run,
    budget_spent,
    check_not_run,
    checkpointed_rows,
    folder_lock,
    training_seconds,
)
from roverswarm.steering import FAILED_MARGIN, KEEP_OUT_MARGIN, SHIELD_STEPS, shield_actions
from roverswarm.storage import atomic_write_files, trained_episodes

CHECK_OBSERVATIONS = 256
"""Swarm observations of random layouts on which every export is checked against JAX."""


@dataclass(frozen=True)
class ExportConfig:
    """Write one seed's trained actor as an ONNX model, with what its inputs mean, a NumPy
    observation function and a snippet that runs it with onnxruntime (no JAX needed)."""

    run: tyro.conf.Positional[Path]
    """A finished run folder of `roverswarm train --out`."""
    out: Path
    """Export folder (policy.onnx, policy.json, observation.py, README.md)."""
    seed: int = 0
    """Which of the run's seeds to export."""
    shield: bool = False
    """Export the safety layer with the model (policy.json's `shield`; observation.py's
    `shield_actions` applies it), for a run trained without it; a run trained behind it
    (train --shield) always exports it."""


@dataclass(frozen=True)
class Export:
    """What :func:`export_run` wrote, and how far the model's actions are from JAX's."""

    files: dict[str, Path]
    meta: dict
    difference: float | None
    """Largest |ONNX - JAX| action entry on :data:`CHECK_OBSERVATIONS` observations (None
    without onnxruntime)."""


def _onnx():
    try:
        import onnx  # noqa: F401
    except ImportError:
        raise UserError('roverswarm export needs the onnx package: pip install -e ".[export]"') from None
    from roverswarm import export_onnx

    return export_onnx


def weights_of(run: Run, seed: int):
    """Seed ``seed``'s (actor parameters, observation normaliser or None) as NumPy arrays."""
    actor, norm = learner_family(run.config.learner.algo).weights(run.learner)
    return jax.tree.map(lambda x: np.asarray(x[seed]), (actor, norm))


def view_of(config: TrainConfig) -> dict:
    """How the exported model sees the swarm (``policy.json``'s ``view``)."""
    network, k, poi_order = config.learner.network, config.learner.entity_nearest, config.learner.poi_order
    if network == "mlp":
        order = "each group nearest first" if config.nearest_first else "each group in index order"
        return {"kind": "flat", "nearest_first": config.nearest_first, "order": order}
    pois = {
        "nearest": "",
        "free": " (those with a positive claim lead first)",
        "matched": " (the rover's POI in the greedy matching, crossing routes swapped, open POIs handed to rovers "
        "whose POI is observed, first; its claim feature is that matching)",
    }[poi_order]
    return {  # --network entity (every entity, or the K nearest of each type) or nearest (K)
        "kind": "entity",
        "nearest": k,
        "poi_order": poi_order,
        "own_features": list(export_numpy.OWN_FEATURES),
        "token_features": list(export_numpy.TOKEN_FEATURES),
        "order": "other rovers (index order, skipping the rover), then POIs, then traps"
        if k == 0
        else f"the {k} nearest other rovers, then POIs{pois}, then traps, each nearest first; empty tokens "
        "(mask False) where a type has fewer",
    }


def _flat_layout(params: EnvParams) -> list[dict]:
    parts = [("own velocity", 2), ("own position", 2), ("POIs, relative", 2 * params.num_pois)]
    parts += [("traps, relative", 2 * params.num_traps), ("other rovers, relative", 2 * (params.num_rovers - 1))]
    layout, start = [], 0
    for what, width in parts:
        layout.append({"what": what, "start": start, "stop": start + width})
        start += width
    return layout


def _off_policy(config: TrainConfig) -> bool:
    return learner_family(config.learner.algo) is offpolicy.FAMILY


def policy_model(config: TrainConfig, params: EnvParams, actor, obs_norm, doc: str):
    """The ONNX model of ``actor`` (one seed's parameters) trained by ``config`` on ``params``:
    an off-policy actor (tanh; one per rover [N, ...] or one shared [1, ...] with rover ids,
    or shared over the nearest view; the observation normaliser first) or the on-policy
    family's (a Gaussian's mean, clipped; the flat view with rover ids, or the entity or
    nearest view)."""
    graphs = _onnx()
    learner = config.learner
    k, n, o = learner.entity_nearest, params.num_rovers, observation_size(params)
    if learner.network == "entity":
        return graphs.entity_actor(actor["net"]["params"], learner.entity_heads, doc)
    if not _off_policy(config):
        if learner.network == "nearest":
            return graphs.nearest_actor(actor["params"]["MLP_0"], k, config.ppo.activation, "clip", doc)
        return graphs.flat_actor(actor["params"]["MLP_0"], n, o, False, config.ppo.activation, "clip", None, doc)
    per_rover = not learner.share_parameters
    mlp = actor["params"] if per_rover else jax.tree.map(lambda x: x[0], actor["params"])
    norm = None if obs_norm is None else (np.asarray(obs_norm.mean), np.asarray(std(obs_norm)))
    if learner.network == "nearest":  # shared (--share-parameters), without rover ids or normaliser
        return graphs.nearest_actor(mlp, k, "relu", "tanh", doc)
    return graphs.flat_actor(mlp, n, o, per_rover, "relu", "tanh", norm, doc)


def trained_sizes(run: Run) -> list[EnvParams]:
    """The (unpadded) layouts' params of every swarm size the run trained on."""
    sizes = None if run.config.mission is not None else range_sizes(run.config.scenario)
    if sizes is None:
        return [run.params]
    return [get_scenario(f"paper-{n}").replace(nearest_first=run.config.nearest_first) for n in sizes]


def _numbers(x) -> float | list:
    return np.asarray(x, np.float64).tolist()


def env_constants(params: EnvParams) -> dict:
    """``policy.json``'s ``env``: the constants the NumPy observations and safety layer read."""
    names = ("rover_radius", "observe_radius", "trap_radius", "dt", "damping", "mass", "sensitivity")
    return {name: _numbers(getattr(params, name)) for name in names} | {"max_steps": params.max_steps}


SHIELD = {"keep_out_margin": KEEP_OUT_MARGIN, "failed_margin": FAILED_MARGIN, "steps": SHIELD_STEPS}
"""``policy.json``'s ``shield`` for an export with the safety layer: what the NumPy layer reads."""


def describe(run: Run, seed: int, model, shield: bool, episodes: int | None = None) -> dict:
    """``policy.json``: what the model's inputs and output mean, what it was trained for (for
    ``episodes`` per seed, default its config's: fewer where its ``--budget-minutes`` ended it),
    and the safety layer's constants if the export holds it (``shield``, else None)."""
    config, params = run.config, run.params
    view = view_of(config)
    if view["kind"] == "flat":
        view["layout"] = _flat_layout(params)
    io = {
        value.name: [d.dim_param or d.dim_value for d in value.type.tensor_type.shape.dim]
        for value in (*model.graph.input, *model.graph.output)
    }
    return {
        "format": "roverswarm onnx policy 2",  # 2: "shield", the safety layer the actions pass
        "run": str(run.folder),
        "seed": seed,
        "algo": config.learner.algo,
        "network": config.learner.network,
        "one_network_per_rover": _off_policy(config) and not config.learner.share_parameters,
        "any_size": run.any_size,
        "inputs": {name: shape for name, shape in io.items() if name != "actions"},
        "outputs": {"actions": io["actions"]},
        "actions": "each rover's force in [-1, 1]^2 (the environment multiplies it by env.sensitivity); row i of "
        "actions depends only on row i of the inputs",
        "view": view,
        "observation_normaliser": "inside the model" if config.learner.normalize_obs else "none",
        "trained_for": {
            "scenario": config.scenario if config.mission is None else None,
            "mission": config.mission,
            "episodes": config.episodes if episodes is None else episodes,
            "sizes": [
                {"rovers": p.num_rovers, "pois": p.num_pois, "traps": p.num_traps, "map_size": _numbers(p.map_size)}
                for p in trained_sizes(run)
            ],
        },
        "env": env_constants(params),
        "shield": dict(SHIELD, trained_behind=config.learner.shield) if shield else None,
        "not_included": ["critics and value networks", "exploration noise", "optimiser states"],
    }


def model_inputs_of(view) -> dict[str, np.ndarray]:
    """The model's inputs of a JAX observation batch: flat [B, N, O], or an entity view."""
    if hasattr(view, "tokens"):
        return {"own": np.asarray(view.own), "tokens": np.asarray(view.tokens), "mask": np.asarray(view.mask)}
    return {"obs": np.asarray(view)}


def random_states(params: EnvParams, count: int, seed: int = 0) -> EnvState:
    """``count`` states [count, ...] of ``params``'s sizes: every entity uniform in the map,
    rovers moving at random, about half the POIs observed, no rover failed."""
    rng = np.random.default_rng(seed)
    n, p, size = params.num_rovers, params.num_pois, float(np.max(params.map_size))
    uniform = lambda k: rng.uniform(-size, size, (count, k, 2)).astype(np.float32)  # noqa: E731
    return EnvState(
        rover_pos=uniform(n),
        rover_vel=rng.normal(size=(count, n, 2)).astype(np.float32),
        poi_pos=uniform(p),
        trap_pos=uniform(params.num_traps),
        observed=rng.random((count, p)) < 0.5,
        time=np.zeros(count, np.int32),
        fail_step=np.full((count, n), NEVER, np.int32),
    )


def check_model(run: Run, seed: int, meta: dict, model_bytes: bytes, count: int = CHECK_OBSERVATIONS) -> float | None:
    """Largest |ONNX - JAX| over the actions of ``count`` swarms of random layouts (the run's
    largest trained size), behind the NumPy and the JAX safety layer if ``meta`` holds it; None
    if onnxruntime is not installed."""
    try:
        import onnxruntime
    except ImportError:
        return None
    family, params = learner_family(run.config.learner.algo), trained_sizes(run)[-1]
    acting = family.acting(run.config)
    view = jax.vmap(family.view(acting) or observe, in_axes=(0, None))

    @jax.jit
    def views_and_actions(states, weights):
        views = view(states, params)
        actions = family.act(acting, weights, views, None)
        if meta["shield"]:
            actions = jax.vmap(shield_actions, in_axes=(0, 0, None))(states, actions, params)
        return views, actions

    states = random_states(params, count)
    views, expected = views_and_actions(states, weights_of(run, seed))
    session = onnxruntime.InferenceSession(model_bytes, providers=["CPUExecutionProvider"])
    (actions,) = session.run(["actions"], model_inputs_of(views))
    if meta["shield"]:
        layer = export_numpy.shield_actions
        actions = np.stack([layer(meta, a, *s) for a, s in zip(actions, zip(*_swarms(states)), strict=True)])
    return float(np.max(np.abs(actions - np.asarray(expected))))


def _swarms(states: EnvState) -> tuple[np.ndarray, ...]:
    """What the NumPy safety layer reads of a batch of states: rover positions, velocities,
    trap positions and which rovers have failed."""
    failed = np.asarray(jax.vmap(failed_rovers)(states))
    return np.asarray(states.rover_pos), np.asarray(states.rover_vel), np.asarray(states.trap_pos), failed


SNIPPET = """\
import json

import numpy as np
import onnxruntime as ort

from observation import model_inputs  # the NumPy observation functions beside the model

meta = json.load(open("policy.json"))
session = ort.InferenceSession("policy.onnx")
size = meta["trained_for"]["sizes"][0]  # or any size, for a policy with "any_size": true
n, p, t = size["rovers"], size["pois"], size["traps"]
rng = np.random.default_rng(0)
rover_pos, rover_vel = rng.uniform(-1, 1, (n, 2)), np.zeros((n, 2))  # your state estimates, in the map's frame
poi_pos, trap_pos = rng.uniform(-1, 1, (p, 2)), rng.uniform(-1, 1, (t, 2))
inputs = model_inputs(meta, rover_pos, rover_vel, poi_pos, trap_pos)
(actions,) = session.run(["actions"], inputs)  # [1, N, 2]: each rover's force in [-1, 1]^2
if meta.get("shield"):  # exported with the safety layer: it turns actions headed into a crater or a rover
    from observation import shield_actions

    actions = shield_actions(meta, actions, rover_pos, rover_vel, trap_pos)[None]
print(actions[0])
"""
"""Runs an exported policy with onnxruntime and NumPy alone (in the export folder); the
same text is in docs/export.md, and a test runs it there."""


def layer_text(shield: dict) -> str:
    """The export README's paragraph on the safety layer it holds."""
    how = "was trained behind it" if shield["trained_behind"] else "was trained without it (`export --shield`)"
    return (
        "The safety layer is exported with the model (`policy.json`: `shield`): apply `shield_actions` of "
        "`observation.py` to the model's actions, as the snippet does. It turns any action whose velocity would "
        "carry a rover into a crater or another rover within a few steps along the tangent of the obstacle's "
        f"keep-out circle. The policy {how}.\n\n"
    )


def readme(meta: dict) -> str:
    """The export folder's README.md."""
    shapes = "\n".join(f"- `{name}`: {shape}" for name, shape in {**meta["inputs"], **meta["outputs"]}.items())
    return (
        f"# {meta['algo']} policy exported by roverswarm (seed {meta['seed']} of {meta['run']})\n\n"
        "`policy.onnx` is the trained actor: deterministic actions, no critic, no exploration noise. "
        "`policy.json` says what its inputs mean; `observation.py` computes them from a swarm's state "
        "with NumPy alone.\n\n"
        f"Inputs and output:\n\n{shapes}\n\n"
        f"View: {meta['view']['kind']} ({meta['view']['order']}).\n\n"
        + (layer_text(meta["shield"]) if meta["shield"] else "")
        + "Run it with `pip install onnxruntime numpy`, in this folder:\n\n"
        f"```python\n{SNIPPET}```\n"
    )


def _check_replaceable(out: Path, files: dict[str, Path]) -> None:
    """Refuse an ``out`` that holds any of the export's files but no earlier export (a
    ``policy.json`` of ours): they are the user's (a project's README.md) and would be replaced."""
    clash = [name for name, path in files.items() if path.exists()]
    try:
        earlier = json.loads((out / "policy.json").read_text())["format"].startswith("roverswarm onnx policy")
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        earlier = False
    require(
        not clash or earlier,
        f"--out '{out}' holds {', '.join(clash)} and no earlier roverswarm export: the export would replace "
        "them; give an empty or new folder",
    )


def export_run(run_folder: str | Path, out: str | Path, seed: int = 0, shield: bool = False) -> Export:
    """Export seed ``seed`` of the finished run in ``run_folder`` into folder ``out`` (see the
    module docstring), with the safety layer if ``shield`` or if the run was trained behind it;
    a run is finished when its checkpoint holds all its episodes or its ``--budget-minutes``
    ended it. :class:`UserError` for a folder that holds no finished run, a seed out of range,
    or a policy ensemble."""
    _onnx()
    run, out = Run(run_folder), Path(out)
    config = run.config
    done = trained_episodes(run.folder / CHECKPOINT)
    # finished: all its episodes, or its --budget-minutes spent (as a sweep counts it; `train --resume` then refuses)
    require(
        done >= config.episodes or budget_spent(config, training_seconds(checkpointed_rows(run.folder)[1])),
        f"'{run.folder}' is not a finished run: its checkpoint holds {done} of {config.episodes} episodes; "
        f"finish it with `roverswarm train --resume {run.folder}`",
    )
    require(
        isinstance(seed, int) and 0 <= seed < config.seeds,
        f"--seed must be in [0, {config.seeds}) for '{run.folder}' (its number of seeds), got {seed}",
    )
    require(
        config.learner.ensemble == 1,
        f"'{run.folder}' is a policy ensemble (--ensemble {config.learner.ensemble}: each rover draws one of its "
        "sub-policies per episode), which cannot be exported; export a run with --ensemble 1",
    )
    check_not_run(out)  # the run's own folder (or another's): its files stay the run's alone
    actor, norm = weights_of(run, seed)
    doc = f"roverswarm {config.learner.algo} actor, seed {seed} of {run.folder}"
    model = policy_model(config, run.params, actor, norm, doc)
    meta = describe(run, seed, model, shield or config.learner.shield, done)
    model.metadata_props.add(key="roverswarm", value=json.dumps(meta))
    model_bytes = model.SerializeToString()
    source = Path(export_numpy.__file__).read_text()
    contents = {
        "policy.onnx": model_bytes,
        "policy.json": json.dumps(meta, indent=2) + "\n",
        "observation.py": source,
        "README.md": readme(meta),
    }
    difference = check_model(run, seed, meta, model_bytes)
    files = {name: out / name for name in contents}
    with folder_lock(out):
        _check_replaceable(out, files)
        atomic_write_files({files[name]: content for name, content in contents.items()})
    return Export(files=files, meta=meta, difference=difference)
