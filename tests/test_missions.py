"""Missions: file validation, layouts, mission metrics, rover failures, the oracle, the commands."""

from __future__ import annotations

import csv
from pathlib import Path

import imageio.v2 as imageio
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from roverswarm.cli import main
from roverswarm.env.mars import NEVER, EnvParams, observe_radii, reset, step_env
from roverswarm.env.missions import MAX_BYTES, MAX_ENTRIES, load_mission, parse_mission
from roverswarm.errors import UserError
from roverswarm.mission import load_policy, markdown_table, parse_failures, run_mission
from roverswarm.oracle import OraclePlan, oracle_goals
from roverswarm.policies import ORACLE, RANDOM, Policy
from roverswarm.rollout import EpisodeStats, MissionStats, Rollout, rollout
from roverswarm.stress import stress_mission

EXAMPLES = Path(__file__).parent.parent / "examples"


def good() -> dict:
    return {
        "name": "test",
        "rovers": {"start": [[-0.5, -0.8], [0.5, -0.8]]},
        "pois": [{"name": "a", "position": [-0.5, 0.5]}, {"position": [0.5, 0.5], "radius": 0.2}],
        "traps": [{"position": [0.0, 0.0], "radius": 0.15}],
    }


def with_change(change) -> dict:
    data = good()
    change(data)
    return data


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["pois"][0].update(position=[1.5, 0.0]), "pois[0] 'a' position: (1.5, 0) is outside the map"),
        (lambda d: d["rovers"]["start"].__setitem__(1, [0.1, 0.0]), "rovers.start[1] overlaps traps[0]"),
        (
            lambda d: d["pois"][0].update(position=[0.05, 0.15]),
            "pois[0] 'a' cannot be observed without touching traps[0]: a rover (radius 0.15) within 0.1 of it "
            "would be in the crater; "
            "move it more than 0.2 from the trap's centre",
        ),
        (lambda d: d["rovers"]["start"].__setitem__(1, [-0.4, -0.8]), "rovers.start[1] overlaps rovers.start[0]"),
        (lambda d: d["traps"][0].update(radius=-0.1), "traps[0] radius: must be a positive number from 1.2e-38 to"),
        (
            lambda d: d["pois"][1].update(radius=0),
            "pois[1] radius: must be a positive number from 1.2e-38 to 1.0e+04, got 0",
        ),
        # squared distances across the map would overflow float32 (the oracle failed with a traceback)
        (lambda d: d.update(map_size=1e20), "map_size: must be a positive number from 1.2e-38 to 1.0e+04, got 1e+20"),
        (lambda d: d["traps"][0].update(radius=1e-300), "traps[0] radius: must be a positive number"),  # 0 as float32
        (lambda d: d["pois"][0].update(radius=1e39), "pois[0] 'a' radius: must be a positive number"),  # inf as float32
        (lambda d: d["pois"][1].pop("position"), "pois[1]: missing field 'position'"),
        (lambda d: d.pop("rovers"), "mission file: missing field 'rovers'"),
        (lambda d: d["traps"][0].update(depth=3), "traps[0]: unknown field 'depth'"),
        (lambda d: d.update(map_size=-1), "map_size: must be a positive number"),
        (lambda d: d.update(episode_length=0), "episode_length: must be an integer from 1 to 2^31 - 1"),
        (lambda d: d.update(pois=[]), "pois: a mission needs at least one POI"),
        (lambda d: d["pois"][0].update(position=[0.1]), "pois[0] 'a' position: expected a position [x, y]"),
        (lambda d: d.update(rovers={"count": 2}), "rovers: give either 'start'"),
        (
            lambda d: d.update(rovers={"count": 0, "release_zone": {"low": [0, 0], "high": [1, 1]}}),
            "rovers.count: must be an integer in [1, 1000]",
        ),
        (
            lambda d: d.update(rovers={"count": 2, "release_zone": {"low": [0, 0], "high": [0, 1]}}),
            "must be below and left of high",
        ),
        (
            lambda d: d.update(rovers={"count": 9, "release_zone": {"low": [0, 0], "high": [0.5, 0.5]}}),
            "9 rovers of radius 0.15 need an area",
        ),
        (lambda d: d["rovers"].update(count=True), "rovers.count: must be an integer (the number of starts), got True"),
        (lambda d: d["rovers"].update(count="2"), "rovers.count: must be an integer (the number of starts), got '2'"),
        (lambda d: d["rovers"].update(count=3), "rovers.count (3) differs from the 2 start positions"),
        (lambda d: d["pois"].__setitem__(1, [0.5, 0.5]), "pois[1]: expected a mapping"),
        (lambda d: d["pois"][1].update(name="a"), "pois[1]: the name 'a' is already used by pois[0]"),
        (lambda d: d["pois"][1].update(name=7), "pois[1] name: must be a non-empty string, got 7"),
        (lambda d: d.update(name=None), "name: must be a non-empty string, got None"),
        (lambda d: d.update(map_size=10**400), "map_size: must be a positive number"),
        (
            lambda d: d["traps"][0].update(position=[0.0, float("nan")]),
            "traps[0] position: expected a position [x, y] of two numbers",
        ),
    ],
)
def test_each_kind_of_bad_mission_names_the_offending_entry(change, message):
    with pytest.raises(UserError) as error:
        parse_mission(with_change(change))
    assert message in str(error.value)


def test_a_release_zone_mostly_in_craters_is_refused_and_one_mostly_clear_starts_no_rover_in_a_crater():
    def zone(half: float, radius: float) -> dict:
        return {
            "rovers": {"count": 2, "release_zone": {"low": [-half, -half], "high": [half, half]}},
            "pois": [{"position": [0.9, 0.9]}],
            "traps": [{"position": [0.0, 0.0], "radius": radius}],
        }

    # a rover's centre must stay 0.15 + 0.55 = 0.7 from the centre: no point of [-0.5, 0.5]^2 is clear
    with pytest.raises(UserError, match=r"rovers.release_zone: 0% of it .* is clear of the traps"):
        parse_mission(zone(0.5, 0.55))
    # [-1, 1]^2 less a disc of radius 0.7 round the centre: 62% clear (1 - pi 0.49 / 4), accepted
    params = parse_mission(zone(1.0, 0.55)).params
    starts = jax.vmap(reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), 500), params)[1].rover_pos
    assert np.linalg.norm(np.asarray(starts), axis=-1).min() >= 0.7 - 1e-6
    # the same zone with a crater of radius 0.85 (1.0 from its centre) is 21% clear: refused
    with pytest.raises(UserError, match="need at least 35% of it clear"):
        parse_mission(zone(1.0, 0.85))


def test_a_poi_on_a_craters_rim_is_accepted_when_a_rover_can_observe_it_from_outside():
    # trap radius 0.15 + rover radius 0.15 - observation radius 0.1: observable beyond 0.2
    mission = parse_mission(with_change(lambda d: d["pois"][0].update(position=[0.0, 0.21])))
    np.testing.assert_allclose(mission.params.fixed_pois[0], [0.0, 0.21])
    with pytest.raises(UserError, match="cannot be observed"):
        parse_mission(with_change(lambda d: d["pois"][0].update(position=[0.0, 0.19])))


def test_small_files_cannot_exhaust_memory_or_time(tmp_path):
    # a YAML alias bomb: 9 levels of 9 aliases each would expand to 9^9 items
    bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8)
    )
    (tmp_path / "bomb.yaml").write_text(bomb)
    with pytest.raises(UserError, match=r"YAML aliases \(\*a\) are not allowed"):
        load_mission(tmp_path / "bomb.yaml")
    (tmp_path / "big.yaml").write_text("#" * (MAX_BYTES + 1))
    with pytest.raises(UserError, match=f"at most {MAX_BYTES} are read"):
        load_mission(tmp_path / "big.yaml")
    many = with_change(lambda d: d.update(pois=[{"position": [0.0, 0.0]}] * (MAX_ENTRIES + 1)))
    with pytest.raises(UserError, match=f"pois: at most {MAX_ENTRIES} entries, got {MAX_ENTRIES + 1}"):
        parse_mission(many)
    # the largest allowed list with a repeated name: the message names both entries
    names = with_change(
        lambda d: d.update(pois=[{"name": f"p{i}", "position": [0.0, 0.0]} for i in range(MAX_ENTRIES)])
    )
    names["pois"][-1]["name"] = "p0"
    with pytest.raises(UserError, match=rf"pois\[{MAX_ENTRIES - 1}\]: the name 'p0' is already used by pois\[0\]"):
        parse_mission(names)


def test_rover_start_lists_are_capped_and_checked_without_comparing_every_pair(tmp_path, monkeypatch):
    import roverswarm.env.missions as missions

    too_many = with_change(lambda d: d["rovers"].update(start=[[0.0, 0.0]] * (MAX_ENTRIES + 1)))
    with pytest.raises(UserError, match=f"rovers.start: at most {MAX_ENTRIES} positions, got {MAX_ENTRIES + 1}"):
        parse_mission(too_many)
    # the largest list allowed, far apart on a wide map: every start is compared with the few
    # starts near it, not with all the earlier ones (counted through the distance function)
    starts = [[-9.5 + 0.6 * (i % 32), -9.5 + 0.6 * (i // 32)] for i in range(MAX_ENTRIES)]
    data = {"map_size": 10.0, "rovers": {"start": starts}, "pois": [{"position": [9.9, 9.9]}]}
    calls = []
    real = np.linalg.norm
    monkeypatch.setattr(missions.np.linalg, "norm", lambda *a, **k: calls.append(1) or real(*a, **k))
    assert parse_mission(data).params.num_rovers == MAX_ENTRIES
    assert len(calls) < 10 * MAX_ENTRIES  # all pairs: ~500,000
    # an overlap is still found and named, with the earlier start
    data["rovers"]["start"][700] = [starts[3][0] + 0.1, starts[3][1]]
    with pytest.raises(UserError, match=r"rovers.start\[700\] overlaps rovers.start\[3\]"):
        parse_mission(data)


def test_a_mission_file_that_is_not_a_mapping_is_refused():
    with pytest.raises(UserError, match="mission file: expected a mapping"):
        parse_mission([1, 2])


def test_a_bad_mission_file_exits_2_with_one_line(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(with_change(lambda d: d["pois"][1].update(position=[0.2, -3.0]))))
    assert main(["mission", "run", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "pois[1] position: (0.2, -3) is outside the map" in err
    path.write_text("pois: [unclosed")
    assert main(["mission", "run", str(path)]) == 2
    err = capsys.readouterr().err
    assert "is not valid YAML: while parsing a flow sequence" in err and err.count("\n") == 1
    path.write_bytes(b"name: \xff\xfe")
    assert main(["mission", "run", str(path)]) == 2
    assert "is not valid UTF-8" in capsys.readouterr().err
    assert main(["mission", "run", str(tmp_path)]) == 2
    assert "is not a file" in capsys.readouterr().err
    assert main(["mission", "run", str(tmp_path / "missing.json")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_json_and_yaml_missions_give_the_same_layout(tmp_path):
    (tmp_path / "m.json").write_text(__import__("json").dumps(good()))
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(good()))
    a, b = load_mission(tmp_path / "m.json"), load_mission(tmp_path / "m.yaml")
    np.testing.assert_array_equal(a.params.fixed_pois, b.params.fixed_pois)
    assert a.poi_names == b.poi_names == ("a", "poi-1")


# ----------------------------------------------------------------------------- layouts


def test_reset_places_the_mission_layout_and_release_zone_starts_stay_in_the_zone():
    mission = load_mission(EXAMPLES / "mission.yaml")
    _, state = reset(jax.random.PRNGKey(3), mission.params)
    np.testing.assert_allclose(state.poi_pos, mission.params.fixed_pois)
    np.testing.assert_allclose(state.trap_pos, mission.params.fixed_traps)
    np.testing.assert_allclose(state.rover_pos, mission.params.fixed_starts)
    survey = load_mission(EXAMPLES / "survey.yaml")
    states = jax.vmap(reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), 200), survey.params)[1]
    low, high = survey.params.start_zone
    assert np.all((states.rover_pos >= low) & (states.rover_pos <= high))
    assert np.unique(np.asarray(states.rover_pos).reshape(-1, 2), axis=0).shape[0] > 500  # drawn, not fixed
    # training keeps POIs and traps but draws starts anywhere, without termination
    train = survey.training_params()
    starts = jax.vmap(reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), 200), train)[1].rover_pos
    assert np.asarray(starts)[..., 1].max() > 0.5 and not train.terminate_on_complete


# ----------------------------------------------------------------------------- metrics


def scripted_rollout() -> Rollout:
    """Two episodes, 2 rovers, 2 POIs, 4 steps, with answers worked out by hand."""
    pos = np.zeros((2, 5, 2, 2))
    pos[0, :, 0, 0] = [0.0, 0.3, 0.6, 0.6, 0.6]  # rover 0 of episode 0: 0.6 in all
    pos[0, :, 1, 1] = [0.0, 0.0, 0.4, 0.4, 0.4]  # rover 1: 0.4
    pos[1, :, 0] = [[0, 0], [0.3, 0.4], [0.3, 0.4], [0.3, 0.4], [0.3, 0.4]]  # 0.5; rover 1 never moves
    observed = np.zeros((2, 5, 2), bool)
    observed[0, 2:, 0] = True  # POI 0 at step 2, POI 1 at step 3 -> all at 3
    observed[0, 3:, 1] = True
    observed[1, 0:, 1] = True  # episode 1: POI 1 at the start, POI 0 never
    stats = EpisodeStats(
        reward=np.zeros(2),
        agent_rewards=np.zeros((2, 2)),
        collisions=np.array([1.0, 0.0]),
        trap_contacts=np.array([0.0, 2.0]),
        coverage_distance=np.zeros(2),
        pois_observed=observed[:, -1].sum(-1),
    )
    exists = (np.ones((2, 2), bool), np.ones((2, 2), bool), np.ones((2, 0), bool))
    return Rollout(stats, pos, np.zeros((2, 2, 2)), np.zeros((2, 0, 2)), observed, np.zeros((2, 4, 2)), *exists)


def test_mission_metrics_on_scripted_trajectories():
    stats = MissionStats.of(scripted_rollout())
    np.testing.assert_array_equal(stats.first_observed, [[2, 3], [np.nan, 0]])
    np.testing.assert_array_equal(stats.time_to_all, [3, np.nan])
    np.testing.assert_array_equal(stats.success, [True, False])
    np.testing.assert_array_equal(stats.pois_observed, [2, 1])
    np.testing.assert_allclose(stats.path_length, [[0.6, 0.4], [0.5, 0.0]], atol=1e-12)
    np.testing.assert_array_equal(stats.trap_contacts, [0, 2])


def test_mission_complete_terminates_and_the_swarm_stands_still_after():
    params = EnvParams(
        num_rovers=1,
        num_pois=1,
        num_traps=0,
        max_steps=10,
        terminate_on_complete=True,
        fixed_pois=np.array([[0.3, 0.0]]),
        fixed_starts=np.array([[0.0, 0.0]]),
    )
    data = rollout(Policy("right", lambda *_: jnp.array([[1.0, 0.0]])), jax.random.PRNGKey(0), params, 1)
    stats = MissionStats.of(data)
    t = int(stats.time_to_all[0])
    assert stats.success[0] and 0 < t < 10
    x = data.rover_pos[0, :, 0, 0]
    # MPE order: the first step moves by the old (zero) velocity; then it drives until observed and stops
    assert np.all(np.diff(x[1 : t + 1]) > 0) and np.all(x[t:] == x[t])
    assert np.all(data.rewards[0, t:] == 0)
    assert data.stats.coverage_distance[0] == pytest.approx(abs(0.3 - x[-1]), abs=1e-6)


# ----------------------------------------------------------------------------- failures


def test_a_failed_rover_never_moves_again_even_when_pushed():
    mission = load_mission(EXAMPLES / "mission.yaml")
    fail = parse_failures(["1@5", "2@0"], mission.params)
    np.testing.assert_array_equal(fail, [NEVER, 5, 0])
    data = rollout(
        RANDOM, jax.random.PRNGKey(0), mission.params.replace(terminate_on_complete=False), 50, fail_step=fail
    )
    pos = data.rover_pos  # [E, T + 1, N, 2]
    assert np.all(pos[:, 5:, 1] == pos[:, 5:6, 1]) and np.all(pos[:, :, 2] == pos[:, :1, 2])
    # it did move before step 5 (from step 1: the first step moves by the zero start velocity)
    assert np.all(np.abs(np.diff(pos[:, 1:6, 1], axis=1)).sum(-1) > 0)
    assert np.all(np.abs(np.diff(pos[:, 1:, 0], axis=1)).sum(-1) > 0)
    lengths = MissionStats.of(data).path_length
    assert np.all(lengths[:, 2] == 0) and np.all(lengths[:, :2] > 0)
    # pushed: rover 0 overlaps the failed rover 1; the contact force moves only rover 0
    params = EnvParams(num_rovers=2, num_pois=1, num_traps=0)
    _, state = reset(jax.random.PRNGKey(0), params)
    state = state.replace(rover_pos=jnp.array([[0.0, 0.0], [0.1, 0.0]]), fail_step=jnp.array([NEVER, 0], jnp.int32))
    touched = []
    for _ in range(3):
        _, state, _, _, _, info = step_env(state, jnp.zeros((2, 2)), params)
        touched.append(int(info["collisions"][1]))
    np.testing.assert_array_equal(state.rover_pos[1], np.float32([0.1, 0.0]))
    assert state.rover_pos[0, 0] < -0.01 and touched[0] == 1  # it still counts in contacts


@pytest.mark.parametrize(
    "text, message",
    [
        ("1-5", "expected ROVER@STEP"),
        ("3@2", "rover must be in [0, 3)"),
        ("0@25", "step must be in [0, 25)"),
        pytest.param("0@" + "9" * 5000, "expected ROVER@STEP", id="5000-digit step"),  # int() would raise
    ],
)
def test_bad_failures_are_refused(text, message):
    with pytest.raises(UserError, match=message.replace("[", r"\[").replace(")", r"\)")):
        parse_failures([text], load_mission(EXAMPLES / "mission.yaml").params)


def test_a_rover_given_two_failure_steps_is_refused():
    """Not the earlier step silently: the user meant one of them."""
    with pytest.raises(UserError, match="--fail 1@5: rover 1 already fails at step 3; give each rover one --fail"):
        parse_failures(["1@3", "0@2", "1@5"], load_mission(EXAMPLES / "mission.yaml").params)


def test_the_oracle_takes_over_the_poi_of_a_failed_rover():
    params = EnvParams(num_rovers=3, num_pois=3, num_traps=0)
    _, state = reset(jax.random.PRNGKey(0), params)
    pois = jnp.array([[0.0, 0.5], [0.5, 0.5], [-0.9, -0.9]])
    state = state.replace(poi_pos=pois, rover_pos=jnp.array([[0.0, 0.4], [0.5, 0.45], [-0.5, -0.5]]), time=jnp.int32(4))
    plan = OraclePlan(poi=jnp.array([0, 1, 2]), home=state.rover_pos)
    # nobody failed: each rover keeps its POI, observed or not
    np.testing.assert_allclose(oracle_goals(state.replace(observed=jnp.array([True, True, False])), plan, params), pois)
    # rover 2 failed before reaching POI 2: of the two free rovers only the nearer (rover 0) takes it
    state = state.replace(rover_pos=jnp.array([[-0.5, -0.4], [0.5, 0.45], [-0.5, -0.5]]))
    failed = state.replace(observed=jnp.array([True, True, False]), fail_step=jnp.array([NEVER, NEVER, 2], jnp.int32))
    np.testing.assert_allclose(oracle_goals(failed, plan, params), pois[jnp.array([2, 1, 2])])
    # a rover whose own POI is still unobserved does not leave it: rover 1 takes POI 2
    busy = failed.replace(observed=jnp.array([False, True, False]))
    np.testing.assert_allclose(oracle_goals(busy, plan, params), pois[jnp.array([0, 2, 2])])
    # two open POIs, two free rovers: one each, nearest pair first
    params4 = EnvParams(num_rovers=2, num_pois=4, num_traps=0)
    four = state.replace(
        rover_pos=jnp.array([[0.0, 0.0], [1.0, 0.0]]),
        poi_pos=jnp.array([[0.0, 0.05], [1.0, 0.05], [0.1, 0.0], [0.2, 0.0]]),
        observed=jnp.array([True, True, False, False]),
        fail_step=jnp.array([NEVER, NEVER], jnp.int32),
    )
    goals = oracle_goals(four, OraclePlan(poi=jnp.array([0, 1]), home=four.rover_pos), params4)
    np.testing.assert_allclose(goals, [[0.1, 0.0], [0.2, 0.0]])


def test_with_a_rover_down_the_oracle_loses_only_missions_it_cannot_finish_without_touching():
    """Every failure ``mission stress`` can draw on the example mission (its starts are fixed and
    the oracle is deterministic: each rover failing at each step before the oracle would have
    finished, 36 cases): the oracle's steering, which the safety layer shares, keeps a smaller
    margin round a failed rover (it stands still), so a POI the failed rover stands against stays
    in reach; it touches no failed rover, and the missions it loses leave a POI no working rover
    can observe without touching the failed one (3 of 36, each under the failed rover's body).
    With the working rovers' margin round failed rovers too, it lost a fourth, whose POI stood
    0.247 from the failed rover's centre."""
    mission = load_mission(EXAMPLES / "mission.yaml")
    params, key, n = mission.params, jax.random.PRNGKey(0), mission.params.num_rovers
    finish = int(MissionStats.of(rollout(ORACLE, key, params, 1)).time_to_all[0])
    rover, when = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(finish), indexing="ij"))
    fail_step = np.full((rover.size, n), NEVER, np.int32)
    fail_step[np.arange(rover.size), rover] = when
    data = rollout(ORACLE, key, params, rover.size, fail_step=fail_step)
    stats = MissionStats.of(data)
    lost = np.flatnonzero(~stats.success)
    assert 0 < len(lost) < 0.15 * rover.size and stats.collisions.sum() == 0
    untouched = 2 * params.rover_radius - observe_radii(params)  # a POI nearer the failed rover needs a touch
    for e in lost:
        gap = np.linalg.norm(data.poi_pos[e] - data.rover_pos[e, -1, rover[e]], axis=-1)
        open_pois = ~data.observed[e, -1]
        assert np.all(gap[open_pois] < untouched[open_pois]), (rover[e], when[e], gap)


@pytest.mark.parametrize("name", ["mission.yaml", "survey.yaml", "outpost.yaml"])
def test_the_oracle_completes_the_example_missions(name):
    mission = load_mission(EXAMPLES / name)
    stats = MissionStats.of(rollout(ORACLE, jax.random.PRNGKey(0), mission.params, 20))
    assert stats.success.all(), stats.first_observed
    assert np.all(stats.time_to_all < mission.params.max_steps)


# ----------------------------------------------------------------------------- commands


def test_a_poi_name_with_a_bar_stays_in_its_column_of_the_report():
    table = markdown_table(["POI", "first observed (step)"], [["a|b", 3.0]]).splitlines()
    assert table[2] == "| a\\|b | 3 |"
    assert all(line.replace("\\|", "").count("|") == 3 for line in table), table


def test_mission_stress_prints_its_markdown_table_one_row_per_line(tmp_path, capsys, monkeypatch):
    """Piped (80 columns), the table a user may paste into a report keeps each row on one line."""
    monkeypatch.setenv("COLUMNS", "80")
    mission = str(EXAMPLES / "mission.yaml")
    assert main(["mission", "stress", mission, "--policy", "random", "--episodes", "8", "--out", str(tmp_path)]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("|")]
    assert len(table) == 2 + 4 and max(map(len, table)) > 80, table
    assert all(line.endswith("|") and line.count("|") == table[0].count("|") for line in table), table


def test_mission_run_writes_routes_animation_and_metrics(tmp_path, capsys):
    out = tmp_path / "out"
    assert (
        main(["mission", "run", str(EXAMPLES / "mission.yaml"), "--out", str(out), "--fail", "2@3", "--fail", "0@40"])
        == 2
    )
    assert "--fail 0@40: step must be in [0, 25)" in capsys.readouterr().err
    result = run_mission(EXAMPLES / "mission.yaml", "oracle", out, ("2@3",))
    rows = list(csv.DictReader(open(out / "trajectories.csv")))
    end = int(result.stats.time_to_all[0])  # the mission stops when complete: the rows end there
    assert end < 25 and len(rows) == (end + 1) * 3
    still = [(r["x"], r["y"]) for r in rows if r["rover"] == "2" and int(r["step"]) >= 3]
    assert len(set(still)) == 1 and all(
        r["working"] == "False" for r in rows if r["rover"] == "2" and int(r["step"]) >= 3
    )
    # the metrics, recomputed from the trajectories with the mission's POI positions and radii
    mission = load_mission(EXAMPLES / "mission.yaml")
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows]).reshape(end + 1, 3, 2)
    near = (
        np.linalg.norm(xy[:, :, None] - mission.params.fixed_pois[None, None], axis=-1) < mission.params.observe_radius
    )
    first = [int(np.argmax(near[:, :, j].any(axis=1))) for j in range(3)]
    assert all(near[:, :, j].any() for j in range(3))
    metrics = list(csv.DictReader(open(out / "metrics.csv")))
    assert [int(float(metrics[0][f"observed_{n}"])) for n in mission.poi_names] == first
    assert int(float(metrics[0]["time_to_all"])) == max(first) and metrics[0]["success"] == "True"
    length = np.linalg.norm(np.diff(xy[:, 2], axis=0), axis=-1).sum()
    assert float(metrics[0]["path_length_rover_2"]) == pytest.approx(length, rel=1e-5)
    np.testing.assert_allclose(result.stats.path_length[0, 2], length, rtol=1e-5)
    assert "rover 2 at step 3" in (out / "metrics.md").read_text()
    frames = imageio.mimread(out / "mission.gif")
    assert len(frames) == 26 and imageio.imread(out / "routes.png").std() > 10
    # a failure scheduled after the mission ended is reported as not reached, and never happened
    late = run_mission(EXAMPLES / "mission.yaml", "oracle", tmp_path / "late", ("2@20",))
    assert late.stats.success[0] and late.stats.time_to_all[0] < 20
    report = (tmp_path / "late" / "metrics.md").read_text()
    assert f"rover 2 at step 20 (not reached: the episode ended at step {late.stats.time_to_all[0]:.0f})" in report
    assert "| 20 (not reached) |" in report
    assert all(r["working"] == "True" for r in csv.DictReader(open(tmp_path / "late" / "trajectories.csv")))


def test_training_a_lone_rover_with_failures_is_refused(tmp_path, capsys):
    """A one-rover mission with --fail-rate would fail its only rover (mission stress refuses it
    too): one line, exit 2, nothing written."""
    mission = tmp_path / "one.yaml"
    mission.write_text("rovers:\n  start: [[0.0, 0.0]]\npois:\n  - position: [0.5, 0.5]\n")
    out = tmp_path / "run"
    assert main(["train", "--mission", str(mission), "--fail-rate", "0.5", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--fail-rate needs at least 2 rovers (one fails, one keeps working), got 1" in err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize("checkpoint", [True, False], ids=["run", "killed-before-its-checkpoint"])
@pytest.mark.parametrize("command", ["run", "stress"])
def test_the_mission_commands_refuse_an_out_folder_holding_a_training_run(command, checkpoint, tmp_path, capsys):
    """`--policy RUN --out RUN` overwrote the run's metrics.csv, and `train --resume RUN` then found
    it damaged: a folder with a run's config.json is refused, before any work, with its
    checkpoint or without (a run killed before its first, which `train` would start anew)."""
    run = tmp_path / "run"
    run.mkdir()
    names = ["checkpoint.npz", "config.json", "metrics.csv"] if checkpoint else ["config.json", "metrics.csv"]
    for name in names:
        (run / name).write_text(f"the run's {name}")
    assert main(["mission", command, str(EXAMPLES / "mission.yaml"), "--episodes", "2", "--out", str(run)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"--out: '{run}' holds a training run (its config.json)" in err
    assert sorted(p.name for p in run.iterdir()) == names
    assert (run / "metrics.csv").read_text() == "the run's metrics.csv"


@pytest.mark.parametrize("command", ["run", "stress"])
def test_the_mission_commands_hold_their_out_folder_from_before_the_episodes(command, tmp_path, monkeypatch, capsys):
    """A file as --out is refused before the episodes run (it was found only after them), and
    while they run the folder is locked: a `train --out` there would be refused, not mixed in."""
    import roverswarm.mission
    import roverswarm.stress
    from roverswarm.runs import folder_lock

    out, seen = tmp_path / "out", []

    def locked_rollout(*args, _original=roverswarm.mission.rollout, **kwargs):
        with pytest.raises(UserError, match="is being written by process"), folder_lock(out):
            pass
        seen.append(True)
        return _original(*args, **kwargs)

    for module in (roverswarm.mission, roverswarm.stress):
        monkeypatch.setattr(module, "rollout", locked_rollout)
    (tmp_path / "file").write_text("a file")
    argv = ["mission", command, str(EXAMPLES / "mission.yaml"), "--episodes", "2", "--out"]
    assert main([*argv, str(tmp_path / "file")]) == 2
    assert "is a file" in capsys.readouterr().err and not seen  # refused before any episode
    assert main([*argv, str(out)]) == 0 and seen


def test_mission_stress_reports_both_conditions_for_policy_and_oracle(tmp_path):
    rows = stress_mission(EXAMPLES / "survey.yaml", "random", tmp_path, episodes=40)
    assert [(r["policy"], r["condition"]) for r in rows] == [
        ("random", "no failure"),
        ("random", "one rover fails"),
        ("oracle", "no failure"),
        ("oracle", "one rover fails"),
    ]
    oracle = {r["condition"]: r for r in rows if r["policy"] == "oracle"}
    assert oracle["no failure"]["success"] == 1.0
    # two rovers must do the work of three: later, or not at all
    assert (
        oracle["one rover fails"]["time_to_all"] > oracle["no failure"]["time_to_all"]
        or oracle["one rover fails"]["success"] < 1
    )
    random = {r["condition"]: r for r in rows if r["policy"] == "random"}
    assert random["no failure"]["success"] < 0.5 < oracle["one rover fails"]["success"]
    assert list(csv.DictReader(open(tmp_path / "stress.csv")))[3]["policy"] == "oracle"
    assert imageio.imread(tmp_path / "stress.png").std() > 10


def _failures_by_hand(key, finish: np.ndarray, n: int, failures: int) -> np.ndarray:
    """random_failures written as a loop: failure j takes the pick-th of the rovers still
    working, from the keys that random_failures documents."""
    fail_step = np.full((len(finish), n), NEVER, np.int32)
    working = [list(range(n)) for _ in finish]
    for j in range(failures):
        k_rover, k_when = jax.random.split(key if j == 0 else jax.random.fold_in(jax.random.fold_in(key, 2), j))
        pick = np.asarray(jax.random.randint(k_rover, (len(finish),), 0, n - j))
        when = np.asarray(jax.random.uniform(k_when, (len(finish),)))
        for e in range(len(finish)):
            fail_step[e, working[e].pop(pick[e])] = int(np.floor(when[e] * finish[e]))
    return fail_step


def test_random_failures_draw_distinct_rovers_uniformly_before_the_finish():
    """K failures per episode: K distinct rovers, each pair of rovers as likely as any other
    (4000 episodes, 5 rovers, K = 2: each of the 10 pairs 10% +- 1.5 points), every step before
    the episode's finish; equal to a plain loop over episodes; one failure drawn exactly as
    before --failures existed (one randint and one uniform from the key's split)."""
    from roverswarm.stress import random_failures

    key, n = jax.random.PRNGKey(3), 5
    finish = np.asarray(jax.random.randint(jax.random.PRNGKey(4), (4000,), 1, 40))
    for failures in (1, 2, 4):
        fail_step = random_failures(key, finish, n, failures)
        np.testing.assert_array_equal(fail_step, _failures_by_hand(key, finish, n, failures))
        failed = fail_step != NEVER
        assert np.all(failed.sum(axis=1) == failures)
        assert np.all(fail_step[failed] < np.repeat(finish, failures)) and np.all(fail_step[failed] >= 0)
    k_rover, k_when = jax.random.split(key)
    one = random_failures(key, finish, n)
    rover = np.asarray(jax.random.randint(k_rover, (len(finish),), 0, n))
    np.testing.assert_array_equal(one.argmin(axis=1), rover)
    when = np.floor(np.asarray(jax.random.uniform(k_when, (len(finish),))) * finish)
    np.testing.assert_array_equal(one.min(axis=1), when)
    pairs = np.unique(random_failures(key, finish, n, 2) != NEVER, axis=0, return_counts=True)[1]
    assert len(pairs) == 10 and np.all(np.abs(pairs / len(finish) - 0.1) < 0.015), pairs
    done = random_failures(key, np.array([0]), 2)  # one episode, complete at reset: at step 0
    assert done.shape == (1, 2) and sorted(done[0].tolist()) == [0, NEVER]


def test_mission_stress_with_two_failures_and_a_refused_count(tmp_path, capsys, monkeypatch):
    """``--failures 2`` on the example mission: the oracle, left with one rover of three,
    finishes less often than with one failure (the same episodes' starts; failures drawn
    alike); the rows say how many rovers failed. ``--failures 3`` leaves no rover, 0 fails
    none, a mission of one rover has none to spare: one line each, exit code 2, nothing
    written, before the policy is loaded."""
    mission = EXAMPLES / "mission.yaml"
    one = {r["condition"]: r for r in stress_mission(mission, "oracle", tmp_path / "one", episodes=60)}
    two = {r["condition"]: r for r in stress_mission(mission, "oracle", tmp_path / "two", episodes=60, failures=2)}
    assert list(two) == ["no failure", "2 rovers fail"]
    assert two["no failure"] == one["no failure"]
    assert two["2 rovers fail"]["success"] < one["one rover fails"]["success"] - 0.1, (one, two)
    assert two["2 rovers fail"]["pois_observed"] < one["one rover fails"]["pois_observed"]
    assert "# Mission 'jezero-delta': 2 rovers fail" in (tmp_path / "two" / "stress.md").read_text()

    def never(*args, **kwargs):
        raise AssertionError("the count is checked before the policy is loaded")

    monkeypatch.setattr("roverswarm.stress.load_policy", never)
    lone = with_change(lambda d: d["rovers"].update(start=[[-0.5, -0.8]]))
    (tmp_path / "lone.yaml").write_text(yaml.safe_dump(lone))
    for path, count, message in (
        (mission, "3", "--failures must be in [1, 2] for 3 rovers (one must keep working), got 3"),
        (mission, "0", "--failures must be in [1, 2] for 3 rovers (one must keep working), got 0"),
        (tmp_path / "lone.yaml", "1", "mission stress needs at least 2 rovers (one fails, one keeps working), got 1"),
    ):
        assert main(["mission", "stress", str(path), "--failures", count, "--out", str(tmp_path / "refused")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and message in err, err
    assert not (tmp_path / "refused").exists()


def test_train_on_a_mission_then_run_the_policy_and_refuse_a_mismatch(tiny_config, tmp_path):
    import dataclasses

    from roverswarm.config import TrainConfig
    from roverswarm.evaluate import evaluate_run
    from roverswarm.runs import Run
    from roverswarm.trainer import train

    # the mission sets the layout, so the scenario stays at its default (as the command line requires)
    file = tmp_path / "mission.yaml"
    original = (EXAMPLES / "mission.yaml").read_text()
    file.write_text(original)
    config = dataclasses.replace(tiny_config, scenario=TrainConfig().scenario, mission=str(file), episodes=200, seeds=1)
    train(config, out=tmp_path / "run")
    mission = load_mission(EXAMPLES / "mission.yaml")
    # the run keeps the file's content: it loads and runs with the file gone ...
    file.unlink()
    assert Run(tmp_path / "run").config.mission_text == original
    policy = load_policy(str(tmp_path / "run"), mission)
    # ... and a resume on an edited file is refused, on the original one accepted
    file.write_text(original.replace("episode_length: 25", "episode_length: 30"))
    with pytest.raises(UserError, match="mission file '.*mission.yaml' changed since this run was trained on it"):
        train(Run(tmp_path / "run").config, out=tmp_path / "run", resume=True, progress=False)
    file.write_text(original)
    train(Run(tmp_path / "run").config, out=tmp_path / "run", resume=True, progress=False)
    data = rollout(policy, jax.random.PRNGKey(0), mission.params, 1)
    np.testing.assert_allclose(data.poi_pos[0], mission.params.fixed_pois)
    rows = evaluate_run(tmp_path / "run", episodes=5)  # on the mission's layout, arrays in its params
    assert [r["policy"] for r in rows] == ["random", "oracle", "maddpg seed 0"] and rows[1]["normalized_score"] == 1.0
    with pytest.raises(
        UserError,
        match=r"trained for 3 rovers, 3 POIs, 3 traps \(mission mission\); "
        r"mission 'crater-survey' has 3 rovers, 6 POIs, 2 traps",
    ):
        load_policy(str(tmp_path / "run"), load_mission(EXAMPLES / "survey.yaml"))
    with pytest.raises(UserError, match=r"--policy-seed must be in \[0, 1\)"):
        load_policy(str(tmp_path / "run"), mission, seed=1)


def test_pettingzoo_runs_a_mission_and_ends_it_once_every_poi_is_observed():
    from roverswarm.env.pettingzoo import RoverSwarmEnv

    data = {"rovers": {"start": [[0.0, 0.0], [0.5, 0.5]]}, "pois": [{"position": [0.05, 0.0]}], "episode_length": 25}
    env = RoverSwarmEnv(params=parse_mission(data).params)
    obs, _ = env.reset(seed=0)
    np.testing.assert_allclose(obs["rover_0"][4:6], [0.05, 0.0], atol=1e-6)  # the POI, relative to rover 0
    _, _, terms, truncs, _ = env.step({a: np.zeros(2, np.float32) for a in env.agents})
    assert all(terms.values()) and not any(truncs.values()) and env.agents == []
    stay = parse_mission({**data, "stop_when_complete": False})
    env = RoverSwarmEnv(params=stay.params)
    env.reset(seed=0)
    assert not any(env.step({a: np.zeros(2, np.float32) for a in env.agents})[2].values())
