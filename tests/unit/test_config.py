import pytest
from pydantic import ValidationError

from services.core.bus import BusConfig
from services.core.config import ConfigError, Frozen, LogLevel, load_config, parse_overrides


class Inner(Frozen):
    a: int = 1
    b: list[str] = []


class Model(Frozen):
    bus: BusConfig = BusConfig()
    inner: Inner = Inner()
    rate: float = 20.0
    name: str = "x"


def test_precedence_defaults_yaml_env_cli(tmp_path):
    y = tmp_path / "c.yaml"
    y.write_text("bus: {connect: [tcp/a:1]}\nsvc:\n  rate: 5\n  name: from-yaml\n  inner: {a: 2}\n")
    env = {"VIEWSCALE_RATE": "7", "VIEWSCALE_INNER__A": "3", "VIEWSCALE_UNRELATED": "1"}
    cfg = load_config(Model, y, ["inner.a=4"], environ=env, section="svc")
    assert cfg.bus.connect == ["tcp/a:1"]  # shared top-level key reaches the section
    assert cfg.name == "from-yaml"  # yaml beats default
    assert cfg.rate == 7.0  # env beats yaml
    assert cfg.inner.a == 4  # cli beats env
    assert cfg.inner.b == []  # untouched default


def test_flow_values_parse():
    assert parse_overrides(["bus.connect=[tcp/127.0.0.1:7447]", "x=true"]) == {
        "bus": {"connect": ["tcp/127.0.0.1:7447"]},
        "x": True,
    }


def test_unknown_field_is_an_error_naming_it(tmp_path):
    with pytest.raises(ConfigError, match="rat"):
        load_config(Model, None, ["rat=3"], environ={})
    # it names what was meant: the same name in its section, or a close spelling (before: pydantic's
    # "Extra inputs are not permitted", for `--set lr=...` when the setting is optim.lr)
    with pytest.raises(ConfigError, match=r"rat: no such setting \(did you mean rate\?\) \(got '3'\)$"):
        load_config(Model, None, ["rat=3"], environ={})
    with pytest.raises(ConfigError, match=r"^invalid Model config: a: no such setting \(did you mean inner.a\?\)"):
        load_config(Model, None, ["a=3"], environ={})
    with pytest.raises(ConfigError, match=r"inner.zzz: no such setting \(inner has a, b\) \(got '3'\)$"):
        load_config(Model, None, ["inner.zzz=3"], environ={})
    with pytest.raises(ConfigError, match=r"zzz: no such setting \(got '3'\)$"):
        load_config(Model, None, ["zzz=3"], environ={})


def test_a_drivers_setting_is_named_as_written_with_what_was_meant():
    """Before: ``driver.ur.hots: no such setting`` (the union's tag in the path, nothing suggested)."""
    from services.camera.config import CameraConfig
    from services.robot.config import RobotConfig

    with pytest.raises(ConfigError, match=r"driver.hots: no such setting \(did you mean driver.host\?\) \(got '1'\)$"):
        load_config(RobotConfig, None, ["driver.type=ur", "driver.host=10.0.0.2", "driver.hots=1"], environ={})
    with pytest.raises(ConfigError, match=r"driver.host: Field required"):
        load_config(RobotConfig, None, ["driver.type=ur"], environ={})
    with pytest.raises(
        ConfigError, match=r"driver.cameras.F.fpss: no such setting \(did you mean driver.cameras.F.fps or fps\?\)"
    ):
        load_config(CameraConfig, None, ["driver={type: opencv, cameras: {F: {source: 0, fpss: 30}}}"], environ={})


def test_a_setting_written_with_its_section_name_says_how_to_write_it(tmp_path):
    """``python -m services.robot --set robot.driver.host=...`` (as a YAML file nests it, and as
    ``viewscale collect --set sim.x=`` takes it); before: ``robot: no such setting``."""
    with pytest.raises(ConfigError, match=r"^--set svc.inner.a=4: .* inside the 'svc' section.*: --set inner.a=4$"):
        load_config(Model, None, ["svc.inner.a=4"], environ={}, section="svc")


def test_bad_override_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="key.path=value"):
        load_config(Model, None, ["rate"], environ={})
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(Model, tmp_path / "nope.yaml", environ={})


def test_config_is_frozen():
    cfg = Model()
    with pytest.raises(ValidationError, match="frozen"):
        cfg.rate = 3.0  # type: ignore[misc]


def test_collecting_tests_that_need_no_model_does_not_import_torch():
    # torch takes seconds to import; only the tests that train or sample may pay for it.
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    code = (
        "import sys, pytest; rc = pytest.main(['--collect-only', '-q', '-p', 'no:cacheprovider', "
        "'tests/unit/test_rig.py', 'tests/unit/test_registry.py', 'tests/integration/test_recorder_service.py']); "
        "print('TORCH', 'torch' in sys.modules, 'RC', rc)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert "TORCH False RC 0" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


class Service(Frozen):
    log_level: LogLevel = "INFO"


def test_log_level_takes_any_case_and_refuses_a_name_that_is_no_level(capsys):
    assert load_config(Service, None, ["log_level=debug"], environ={}).log_level == "DEBUG"
    assert load_config(Service, None, [], environ={"VIEWSCALE_LOG_LEVEL": "Warning"}).log_level == "WARNING"
    # before, an unknown name set the level to INFO without a word
    with pytest.raises(ConfigError, match=r"log_level.*'LOUD' is not a logging level; one of DEBUG, INFO"):
        load_config(Service, None, ["log_level=LOUD"], environ={})
    # the flags of the viewscale CLI and of the router: a usage error naming the flag
    from services.cli import build_parser

    assert build_parser().parse_args(["--log-level", "error", "collect"]).log_level == "ERROR"
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["--log-level", "verbose", "collect"])
    assert exc.value.code == 2 and "argument --log-level: 'verbose' is not a logging level" in capsys.readouterr().err


def test_an_address_open_beyond_loopback_is_told_apart():
    """serve and worker warn when they listen beyond loopback with no token."""
    from services.policy.config import open_to_others

    for loopback in ("127.0.0.1:50051", "localhost:0", "[::1]:7001", "127.0.1.1:80"):
        assert not open_to_others(loopback), loopback
    for open_ in ("0.0.0.0:50051", "[::]:7001", "10.0.0.5:7001", "policy-worker:7001"):
        assert open_to_others(open_), open_


def test_a_misspelt_section_of_the_shared_file_is_an_error_not_ignored(tmp_path):
    """(a file with `recordr:` loaded the recorder's defaults without a word)"""
    y = tmp_path / "c.yaml"
    y.write_text("world: sim\nbus: {connect: [tcp/a:1]}\nrecorder: {rate: 5}\nrecordr: {rate: 9}\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: 'recordr' is no service's section \(sections: sim, camera"):
        load_config(Model, y, section="recorder")
    # every service's section, the shared keys, and the user's own x- keys are fine
    y.write_text("world: sim\nbus: {connect: [tcp/a:1]}\nrecorder: {rate: 5}\nsim: {}\nx-common: &c {a: 1}\n")
    assert load_config(Model, y, section="recorder").rate == 5.0
    from pathlib import Path

    from services.core.config import SECTIONS, SHARED_KEYS, read_yaml

    for shipped in ("sim.yaml", "real.yaml"):  # the shipped files name only these
        keys = set(read_yaml(Path(__file__).resolve().parents[2] / "deploy" / shipped))
        assert keys <= {*SECTIONS, *SHARED_KEYS}, keys
