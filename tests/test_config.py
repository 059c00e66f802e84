"""Config: unknown keys and wrong types name the field; overrides; `ebrl up` exits 2 and starts nothing."""

import dataclasses
import pathlib
import subprocess
import sys

import pytest

from ebrl import config

ROOT = pathlib.Path(__file__).resolve().parent.parent


def write(tmp_path, text):
    path = tmp_path / "c.toml"
    path.write_text(text)
    return str(path)


def test_every_shipped_config_is_valid():
    for path in (ROOT / "configs").glob("*.toml"):
        config.load(str(path))


def test_unknown_key_names_the_field(tmp_path):
    with pytest.raises(config.ConfigError, match=r"unknown key sim\.envs_per_grup.*did you mean sim\.envs_per_group"):
        config.load(write(tmp_path, "[sim]\nenvs_per_grup = 3\n"))


def test_unknown_section(tmp_path):
    with pytest.raises(config.ConfigError, match=r"unknown section \[simulator\]"):
        config.load(write(tmp_path, "[simulator]\ngroups = 3\n"))


@pytest.mark.parametrize(
    "text, error",
    [
        ('[run]\niterations = "ten"\n', r"run\.iterations: expected an integer, got string 'ten'"),
        ("[train]\nlr = true\n", r"train\.lr: expected a number"),
        ('[policy]\nhidden = [64, "x"]\n', r"policy\.hidden\[1\]: expected an integer"),
        ('[run]\nmode = "turbo"\n', r"run\.mode = 'turbo': expected one of"),
        ("[sim]\ngroups = 0\n", r"sim\.groups = 0: must be > 0"),
        ('[run]\nname = "My Run"\n', r"run\.name"),
        ("[run\n", r"not valid TOML"),
    ],
)
def test_wrong_values_name_the_field(tmp_path, text, error):
    with pytest.raises(config.ConfigError, match=error):
        config.load(write(tmp_path, text))


def test_overrides_are_typed(tmp_path):
    cfg = config.load(write(tmp_path, "[run]\niterations = 5\n"),
                      ["run.iterations=2", "env.id=Hopper-v5", "policy.hidden=[32]", "run.seed = 4"])
    assert cfg.run.iterations == 2 and cfg.env.id == "Hopper-v5" and cfg.policy.hidden == [32] and cfg.run.seed == 4
    with pytest.raises(config.ConfigError, match="run.iterations"):
        config.load(write(tmp_path, ""), ["run.iterations=lots"])
    with pytest.raises(config.ConfigError, match="expected section.key=value"):
        config.load(write(tmp_path, ""), ["iterations=3"])


def test_an_empty_override_value_removes_the_key(tmp_path):
    """`--set run.target_return=` runs without the config's target (ebrl bench: a target does not end a window);
    a quoted empty string stays a value."""
    path = write(tmp_path, '[run]\ntarget_return = 900.0\nname = "x"\n[env.kwargs]\nobs = "rgb"\n')
    cfg = config.load(path, ["run.target_return=", "env.kwargs.obs= "])
    assert cfg.run.target_return is None and cfg.env.kwargs == {} and cfg.run.name == "x"
    assert config.load(path, ['log.wandb_group=""']).log.wandb_group == ""
    assert config.load(path, ["run.target_success="]).run.target_return == 900.0  # an absent key: nothing to do


def test_dump_round_trips(tmp_path):
    cfg = config.load(str(ROOT / "configs" / "quickstart.toml"), ['env.kwargs={reset_noise_scale = 0.1}'])
    again = config.load(write(tmp_path, config.dump_toml(cfg)))
    assert again == cfg


def test_keys_with_dots_and_spaces_round_trip_through_the_written_config(tmp_path):
    """The resolved config is written by tomli-w: a kwargs key with a dot, a space, a quote or a non-ASCII letter,
    nested tables and odd strings all read back as they were (the hand-written writer broke on them)."""
    kwargs = '{"obs.kind" = "rgb", "image size" = 84, "say \\"hi\\"" = "a\\nb", "ü" = [1.5, 2], nested = {"a.b" = {c = true}}}'
    cfg = config.load(str(ROOT / "configs" / "quickstart.toml"), [f"env.kwargs={kwargs}", "log.wandb_tags=['x y', 'z.w']"])
    assert cfg.env.kwargs == {"obs.kind": "rgb", "image size": 84, 'say "hi"': "a\nb", "ü": [1.5, 2],
                              "nested": {"a.b": {"c": True}}}
    text = config.dump_toml(cfg)
    assert '"obs.kind" = "rgb"' in text and '"image size" = 84' in text
    again = config.load(write(tmp_path, text))
    assert again == cfg and again.env.kwargs == cfg.env.kwargs and again.log.wandb_tags == ["x y", "z.w"]


def test_nested_overrides_reach_into_tables(tmp_path):
    path = write(tmp_path, '[env]\nkwargs = {obs = "state", image_size = 64}\n')
    cfg = config.load(path, ["env.kwargs.obs=rgb", 'env.kwargs."camera.name"=frontview', "env.kwargs.deep.x=1"])
    assert cfg.env.kwargs == {"obs": "rgb", "image_size": 64, "camera.name": "frontview", "deep": {"x": 1}}
    with pytest.raises(config.ConfigError, match=r"run\.iterations is not a table"):
        config.load(path, ["run.iterations=3", "run.iterations.x=1"])
    with pytest.raises(config.ConfigError, match=r"unknown key env\.kwarg"):
        config.load(path, ["env.kwarg.obs=rgb"])  # a typo above the leaf is still named


@pytest.mark.parametrize("command", ["config", "up", "bench"])
def test_nested_set_on_the_command_line(tmp_path, command):
    """`--set env.kwargs.obs=rgb` is accepted by every command that takes --set (a bad nested value is named the
    same way by each, before anything starts)."""
    args = [sys.executable, "-m", "ebrl.cli", command, str(ROOT / "configs" / "quickstart.toml"),
            "--set", "env.kwargs.obs=rgb", "--set", "env.kwargs.nested.k=2", "--set", "sim.groups.x=1"]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2 and "sim.groups is not a table" in proc.stderr, proc.stderr
    if command == "config":
        proc = subprocess.run(args[:-2], capture_output=True, text=True, timeout=120, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        assert '[env.kwargs]\nobs = "rgb"\n' in proc.stdout and "[env.kwargs.nested]\nk = 2" in proc.stdout


def test_version_flag():
    import ebrl

    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "--version"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == f"ebrl {ebrl.__version__}"


def test_ebrl_up_with_a_typo_exits_2_and_starts_nothing(tmp_path):
    path = write(tmp_path, '[run]\nname = "typo"\noutput_dir = "%s"\n[train]\nbatch_sise = 8\n' % (tmp_path / "runs"))
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "up", path], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "train.batch_sise" in proc.stderr
    assert not (tmp_path / "runs").exists()


def test_describe_lists_every_key_with_type_and_default():
    text = config.describe()
    for name, cls in config.SECTIONS.items():
        assert f"[{name}]" in text
        for f in dataclasses.fields(cls):
            assert f"  {f.name} (" in text
    assert 'mode ("ebrl" | "colocated" | "hybrid" | "async", default "ebrl")' in text
    assert "target_return (float, optional, default absent)" in text


def test_a_config_can_start_from_a_base_file(tmp_path):
    (tmp_path / "shared").mkdir()
    (tmp_path / "shared" / "task.toml").write_text(
        '[run]\nname = "task"\niterations = 7\n[sim]\ngroups = 3\nenvs_per_group = 2\n[train]\nbatch_size = 40\n'
        '[hosts.a]\nservices = ["gen", "train", "sim"]\ncores = [0]\n')
    path = tmp_path / "bench.toml"
    path.write_text('base = "shared/task.toml"\n[run]\nname = "bench"\n[sim]\ngroups = 4\n'
                    '[hosts.a]\nservices = ["gen", "train", "sim"]\n')
    cfg = config.load(str(path), ["sim.envs_per_group=5"])
    assert cfg.run.name == "bench" and cfg.run.iterations == 7  # key by key within a section
    assert (cfg.sim.groups, cfg.sim.envs_per_group) == (4, 5)  # ... and --set over both
    assert cfg.hosts["a"].cores == []  # a [hosts.<name>] table is replaced whole
    # bases chain (relative to each file), and the shipped bench configs use one
    (tmp_path / "more.toml").write_text('base = "bench.toml"\n[train]\nlr = 0.01\n')
    more = config.load(str(tmp_path / "more.toml"))
    assert more.run.name == "bench" and more.sim.groups == 4 and more.train.lr == 0.01
    lift, bench = (config.load(str(ROOT / "configs" / f)) for f in ("robosuite_lift.toml", "bench_lift.toml"))
    assert bench.env == lift.env and bench.policy == lift.policy and bench.train == lift.train


@pytest.mark.parametrize("text, error", [
    ('base = "nowhere.toml"\n', r"nowhere\.toml: no such file \(the base of .*c\.toml\)"),
    ("base = 3\n", r"base = 3: expected the path of another config file"),
    ('base = "c.toml"\n', r"base files form a cycle"),
    ('base = "d.toml"\n', r"base files form a cycle: .*c\.toml -> .*d\.toml -> .*c\.toml"),
])
def test_a_bad_base_is_named(tmp_path, text, error):
    (tmp_path / "d.toml").write_text('base = "c.toml"\n')
    with pytest.raises(config.ConfigError, match=error):
        config.load(write(tmp_path, text))
