"""LIBERO: the suites' catalogue and initial states, the backend, the evaluation protocol's tables.

Without LIBERO installed the catalogue, the init-state reader and the tables run on a made-up benchmark tree; the
tests that build LIBERO's scenes skip, saying why (`make libero` installs it; CI's `.ci/run` does, and runs them
in `make test-slow`).
"""

import importlib.util
import json
import pickle
import time
import zipfile

import numpy as np
import pytest

import helpers
from ebrl.cli import parser
from ebrl import config
from ebrl.envs import EnvError, EnvSpec, describe, make_env
from ebrl.envs import libero_suite
from ebrl.envs.backends import BACKENDS, preflight
from ebrl.evaluate_suite import SuiteResult, TaskResult, published_row

try:
    libero_suite.check()
    READY, WHY = True, ""
except libero_suite.LiberoMissing as exc:
    READY, WHY = False, f"LIBERO is not set up ({exc})"
needs_libero = pytest.mark.skipif(not READY, reason=WHY)
FOUR = ("libero_spatial", "libero_object", "libero_goal", "libero_10")


def torch_save_zip(path, array):
    """What ``torch.save(array)`` writes for a numpy array (LIBERO's .pruned_init files): a zip of its pickle."""
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", pickle.dumps(array, protocol=2))
        archive.writestr("archive/version", "3\n")


@pytest.fixture
def fake_libero(tmp_path, monkeypatch):
    """A benchmark tree with two LIBERO-Spatial tasks and one LIBERO-90 task, and their init states."""
    root = tmp_path / "libero" / "libero"
    (root / "benchmark").mkdir(parents=True)
    names = {"libero_spatial": ["pick_up_the_bowl", "open_the_drawer"], "libero_object": [], "libero_goal": [],
             "libero_10": [], "libero_90": ["KITCHEN_SCENE10_put_the_pot_on_the_stove"]}
    (root / "benchmark" / "libero_suite_task_map.py").write_text(f"libero_task_map = {names!r}\n")
    for suite, tasks in names.items():
        (root / "init_files" / suite).mkdir(parents=True)
        for i, name in enumerate(tasks):
            torch_save_zip(root / "init_files" / suite / f"{name}.pruned_init", np.full((50, 9), float(i)))
    monkeypatch.setattr(libero_suite, "package_dir", lambda: root)
    return root


def test_the_catalogue_reads_the_task_map_and_the_instructions_as_the_benchmark_names_them(fake_libero):
    tasks = libero_suite.tasks_of("libero_spatial")
    assert [(t.index, t.language) for t in tasks] == [(0, "pick up the bowl"), (1, "open the drawer")]
    assert libero_suite.tasks_of("libero_90")[0].language == "put the pot on the stove"  # the scene prefix dropped
    assert tasks[1].init_file == fake_libero / "init_files" / "libero_spatial" / "open_the_drawer.pruned_init"


def test_tasks_are_selected_by_index_name_list_or_all_and_a_wrong_one_names_the_range(fake_libero):
    every = libero_suite.tasks_of("libero_spatial")
    assert libero_suite.select("libero_spatial") == every == libero_suite.select("libero_spatial", [])
    assert libero_suite.select("libero_spatial", 1) == [every[1]]
    assert libero_suite.select("libero_spatial", ["open_the_drawer", 0]) == [every[1], every[0]]
    with pytest.raises(ValueError, match=r"7 is not a task of libero_spatial \(an index 0..1"):
        libero_suite.select("libero_spatial", [7])
    with pytest.raises(ValueError, match="expected one of libero_spatial"):
        libero_suite.tasks_of("libero_100")


def test_init_states_are_read_without_torch_and_a_pickle_of_anything_else_is_refused(fake_libero, tmp_path):
    task = libero_suite.tasks_of("libero_spatial")[1]
    states = libero_suite.init_states(task)
    assert states.shape == (50, 9) and states.dtype == np.float64 and (states == 1.0).all()

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    torch_save_zip(task.init_file, Evil())
    with pytest.raises(pickle.UnpicklingError, match="a numpy array only, not __builtin__.print"):
        libero_suite.init_states(task)


def test_the_backend_is_declared_and_preflight_says_how_to_install_libero_when_it_is_missing(monkeypatch):
    assert BACKENDS["libero"].module == "ebrl.envs.libero"
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    with pytest.raises(EnvError, match=r"needs LIBERO: install it: `make libero`"):
        preflight(EnvSpec("libero_spatial", backend="libero", kwargs={"obs": "state"}))


def test_the_stock_libero_configs_load():
    for name, obs in (("libero_spatial", "rgb"), ("libero_spatial_state", "state")):
        cfg = config.load(str(helpers.ROOT / "configs" / f"{name}.toml"))
        assert cfg.env.backend == "libero" and cfg.env.id == "libero_spatial" and cfg.env.kwargs["obs"] == obs
        assert cfg.policy.checkpoint == ""


def test_ebrl_eval_takes_suites_and_tasks():
    args = parser().parse_args(["eval", "runs/x", "--suite", "libero_spatial,libero_goal", "--tasks", "0,9"])
    assert args.suite == ["libero_spatial,libero_goal"] and args.tasks == "0,9" and args.episodes is None


def suite_result(suite, wins):
    tasks = [TaskResult(i, f"task_{i}", f"do thing {i}", [k < w for k in range(50)], [100] * 50, list(range(50)))
             for i, w in enumerate(wins)]
    return SuiteResult(suite, tasks, "runs/x/policy.safetensors", 7, True, 12.0)


def test_the_suite_table_has_a_row_per_task_and_the_suites_rate_with_wilson_intervals():
    result = suite_result("libero_spatial", [50, 45, 0])
    table = result.table()
    assert "LIBERO-Spatial (libero_spatial): runs/x/policy.safetensors v7, 3 tasks, 150 episodes" in table
    assert "45/50   90.0%   78.6% .. 95.7%" in table  # Wilson's 95 % interval of 45 of 50
    assert "0/50    0.0%   0.0% .. 7.1%" in table
    assert "95/150   63.3%" in table.splitlines()[-1]
    saved = json.loads(json.dumps(result.to_json()))
    assert saved["tasks"][1]["success_rate"]["rate"] == 0.9 and saved["success_rate"]["lo"] < 0.634
    row = published_row([result, suite_result("libero_goal", [50, 50, 50])])
    header, _, values = ([cell.strip() for cell in line.split("|")[1:-1]] for line in row.splitlines())
    assert header == ["LIBERO-Spatial", "LIBERO-Goal", "Average"]
    assert values == ["63.3 (55.4-70.6)", "100.0 (97.5-100.0)", "81.7"]  # Wilson's, over each suite's episodes


# --- with LIBERO installed -----------------------------------------------------------------------------------


def libero_env(suite, task, **kwargs):
    kwargs = {"obs": "state", **kwargs, "tasks": [task]}
    return make_env(EnvSpec(suite, backend="libero", kwargs=kwargs))


@pytest.mark.slow
@needs_libero
@pytest.mark.parametrize("suite", FOUR)
def test_every_task_builds_resets_to_its_first_and_last_official_initial_state_and_steps(suite):
    """The issue's acceptance: each task of Spatial, Object, Goal and 10 in EBRL's own env."""
    for task in libero_suite.tasks_of(suite):
        states = libero_suite.init_states(task)
        env = libero_env(suite, task.index, no_op_steps=0)
        try:
            base = env.unwrapped
            assert base.instruction == task.language and base.horizon == libero_suite.MAX_STEPS[suite]
            for j in (0, len(states) - 1):
                obs, info = env.reset(options={"init_state": j})
                assert info["init_state"] == j and obs.shape == env.observation_space.shape
                assert np.allclose(base.env.sim.get_state().flatten(), states[j]), (task.name, j)
                for _ in range(3):
                    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
                    assert np.isfinite(obs).all() and isinstance(info["success"], bool), task.name
        finally:
            env.close()


@pytest.mark.slow
@needs_libero
def test_the_no_op_steps_the_episode_limit_and_the_costs_kept_down():
    env = libero_env("libero_spatial", 0)
    base = env.unwrapped
    try:
        start = time.perf_counter()
        env.reset(seed=3)
        reset_s = time.perf_counter() - start
        assert base.init_state == 3 and base.env.timestep == libero_suite.NO_OP_STEPS
        assert base.env.sim.model._model.narena == 64 << 20  # MuJoCo's arena, not robosuite's ~1.3 GB
        assert reset_s < 0.3, f"a reset took {reset_s:.2f} s: it rebuilt the scene?"
        truncated = False
        for _ in range(base.horizon):
            *_, terminated, truncated, _ = env.step(np.zeros(7, np.float32))
        assert truncated and not terminated
    finally:
        env.close()


@pytest.mark.slow
@needs_libero
def test_the_cameras_proprio_and_instruction_are_fields_and_render_only_when_read():
    env = libero_env("libero_spatial", 0, obs="rgb", image_size=64)
    base = env.unwrapped
    try:
        assert base.obs_layout.describe() == ("agentview:image[3, 64, 64] + wrist:image[3, 64, 64] + "
                                              "proprio:vector[8] + instruction:tokens[16]")
        assert [f.uint8 for f in base.obs_layout.fields[:2]] == [True, True]
        obs, _ = env.reset(seed=0)
        parts = base.obs_layout.split(obs[None])
        assert parts["agentview"].std() > 0.05 and parts["wrist"].std() > 0.02
        base.skip_observation = True
        skipped, *_ = env.step(np.zeros(7, np.float32))
        assert not base.obs_layout.split(skipped[None])["agentview"].any()
        assert base.obs_layout.split(base.observe()[None])["agentview"].std() > 0.05
    finally:
        env.close()


@pytest.mark.slow
@needs_libero
def test_a_whole_suite_is_spread_over_the_envs_with_one_layout():
    spec = EnvSpec("libero_object", backend="libero", kwargs={"obs": "state"})
    envs = [make_env(spec, seed=seed) for seed in (0, 3)]
    try:
        assert [e.unwrapped.task.index for e in envs] == [0, 3]
        assert envs[0].observation_space == envs[1].observation_space
        assert describe(spec).layout == envs[0].unwrapped.obs_layout
    finally:
        for env in envs:
            env.close()


@pytest.mark.slow
@needs_libero
def test_the_state_config_trains_through_ebrl_up_and_ebrl_eval_suite_prints_the_table(tmp_path, capsys):
    code, out, _ = helpers.run_collecting_stats(
        tmp_path / "runs", "configs/libero_spatial_state.toml", "run.iterations=2", "sim.envs_per_group=2",
        "train.batch_size=32", "sim.segment_length=8", run="libero", timeout=600)
    assert code == 0, out
    run_dir = next((tmp_path / "runs").glob("libero-*"))
    from ebrl.evaluate_suite import command

    assert command(str(run_dir), ["libero_spatial"], episodes=2, tasks=[0, 9], workers=2) == 0
    table = capsys.readouterr().out
    assert "LIBERO-Spatial (libero_spatial)" in table and "   9  pick up the black bowl on the wooden cabinet" in table
    saved = json.loads((run_dir / "eval_libero_spatial.json").read_text())
    assert [t["init_states"] for t in saved["tasks"]] == [[0, 1], [0, 1]]
