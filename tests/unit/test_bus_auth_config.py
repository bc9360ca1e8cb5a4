"""Credentials and access-control configuration of the bus: validation, files and their errors.
(The behaviour on a real router: tests/integration/test_bus_auth.py.)"""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
import zenoh
from pydantic import ValidationError

from services.cli import main as viewscale
from services.core.bus import Bus, BusConfig, free_tcp_port, read_password, read_users, router
from services.core.config import ConfigError, Frozen, load_config
from services.router.__main__ import main as router_main
from services.router.credentials import SERVICE_USERS, USERS_FILE, password_path, write_credentials

ACL = Path(__file__).resolve().parents[2] / "deploy" / "zenoh" / "router-acl.json5"


def test_the_default_bus_is_unauthenticated():
    cfg = BusConfig()
    assert (cfg.user, cfg.password_file, cfg.acl_file, cfg.users_file) == (None, None, None, None)


@pytest.mark.parametrize("value", [0, -1, float("nan"), float("inf")])
def test_the_connect_timeout_is_a_positive_number_of_seconds(value):
    # zenoh reads a negative connect timeout as "retry forever": a service would hang without a word
    with pytest.raises(ValidationError, match="connect_timeout_s"):
        BusConfig(mode="client", connect=["tcp/127.0.0.1:7447"], connect_timeout_s=value)


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"mode": "client", "user": "camera"}, "bus.user and bus.password_file go together"),
        ({"mode": "client", "password_file": "x"}, "bus.user and bus.password_file go together"),
        ({"mode": "peer", "user": "camera", "password_file": "x"}, "bus.user needs bus.mode=client"),
        ({"mode": "client", "user": "a:b", "password_file": "x"}, "without ':'"),
        ({"mode": "client", "users_file": "u"}, "configure a router"),
        ({"mode": "router", "acl_file": "a"}, "bus.acl_file needs bus.users_file"),
    ],
)
def test_inconsistent_credentials_are_one_clear_error(fields, message):
    with pytest.raises(ValidationError, match=message):
        BusConfig(**fields)


def test_credentials_come_from_the_environment_like_any_field(tmp_path):
    env = {"VIEWSCALE_BUS__MODE": "client", "VIEWSCALE_BUS__USER": "camera", "VIEWSCALE_BUS__PASSWORD_FILE": "/s/p"}

    class Svc(Frozen):  # a service config: a `bus` section and nothing else
        bus: BusConfig = BusConfig()

    cfg = load_config(Svc, environ=env, yaml_from_env=False)
    assert (cfg.bus.user, cfg.bus.password_file) == ("camera", Path("/s/p"))


def test_a_missing_or_empty_password_file_is_one_clear_error(tmp_path):
    with pytest.raises(ConfigError, match=r"password file of Zenoh user 'camera', .*nope, does not exist"):
        Bus(BusConfig(mode="client", connect=["tcp/127.0.0.1:1"], user="camera", password_file=tmp_path / "nope"))
    empty = tmp_path / "empty"
    empty.write_text("\n")
    with pytest.raises(ConfigError, match="is empty"):
        read_password(empty, "camera")
    secret = tmp_path / "camera.password"
    secret.write_text("s3cret-value\nignored\n")
    assert read_password(secret, "camera") == "s3cret-value"


def test_a_bad_users_file_names_the_file_and_line(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("camera:pw\n\nbroken-line\n")
    with pytest.raises(ConfigError, match=r"users\.txt:3: expected user:password"):
        read_users(users)
    with pytest.raises(ConfigError, match="does not exist"):
        router([f"tcp/127.0.0.1:{free_tcp_port()}"], users_file=tmp_path / "missing.txt")


def test_the_router_refuses_an_acl_file_that_does_not_enable_access_control(tmp_path, capsys):
    write_credentials(tmp_path / "s", ["camera"])
    off = tmp_path / "off.json5"
    off.write_text('{access_control: {enabled: false, default_permission: "deny"}}')
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    assert router_main(["--listen", endpoint, "--users", str(tmp_path / "s" / USERS_FILE), "--acl", str(off)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not enable access control" in err[0]


def test_viewscale_router_refuses_an_acl_without_users_in_its_own_name(tmp_path, capsys):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    assert viewscale(["router", "--listen", endpoint, "--acl", str(ACL)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # one line, not the router module's usage text under the name `python -m services.router`
    assert err == ["error: --acl needs --users: its rules name users that must authenticate"]


def test_the_shipped_acl_names_exactly_the_service_users_and_every_rule_is_used():
    conf = zenoh.Config.from_file(str(ACL))
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert sorted(u for s in acl["subjects"] for u in s["usernames"]) == sorted(SERVICE_USERS)
    rules = {r["id"] for r in acl["rules"]}
    used = {r for p in acl["policies"] for r in p["rules"]}
    assert used == rules, f"rules in no policy: {rules - used}; unknown rules: {used - rules}"
    # Each user may hold a liveliness token on its own name only.
    for user in SERVICE_USERS:
        own = {r for p in acl["policies"] if user in p["subjects"] for r in p["rules"]}
        tokens = {
            k
            for r in acl["rules"]
            if r["id"] in own and "liveliness_token" in r["messages"] and r["flows"] == ["ingress"]
            for k in r["key_exprs"]
        }
        assert tokens <= {f"vs/alive/{user}"}, (user, tokens)


def test_credentials_are_owner_only_and_never_printed(tmp_path, capsys):
    out = tmp_path / "secrets"
    assert viewscale(["credentials", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    lines = (out / USERS_FILE).read_text().splitlines()
    assert [line.split(":", 1)[0] for line in lines] == list(SERVICE_USERS)
    for line in lines:
        user, password = line.split(":", 1)
        assert read_password(password_path(out, user), user) == password and len(password) >= 32
        assert password not in printed
    for path in [out / USERS_FILE, *(password_path(out, u) for u in SERVICE_USERS)]:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    assert stat.S_IMODE(out.stat().st_mode) == 0o700

    # A second run would lock out running services: refused unless --force, which rotates all.
    assert viewscale(["credentials", "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert viewscale(["credentials", "--out", str(out), "--force"]) == 0
    assert (out / USERS_FILE).read_text().splitlines() != lines


def test_credentials_into_a_file_or_under_one_is_one_clear_error_and_changes_nothing(tmp_path, capsys):
    note = tmp_path / "notes.txt"
    note.write_text("keep me\n")
    assert viewscale(["credentials", "--out", str(note)]) == 2
    assert f"--out {note}: not a directory" in capsys.readouterr().err
    assert viewscale(["credentials", "--out", str(note / "secrets")]) == 2
    assert f"--out {note / 'secrets'}: not a directory ({note} is a file)" in capsys.readouterr().err
    assert note.read_text() == "keep me\n" and sorted(tmp_path.iterdir()) == [note]


def test_credentials_of_a_name_given_twice_are_written_once_and_no_name_is_an_error(tmp_path, capsys):
    out = tmp_path / "secrets"
    assert viewscale(["credentials", "--out", str(out), "--users", "operator,viewer,operator"]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith(f"wrote 2 passwords to {out} ") and "operator.password, viewer.password for" in printed
    assert [line.split(":", 1)[0] for line in (out / USERS_FILE).read_text().splitlines()] == ["operator", "viewer"]
    # (an empty --users, as from an unset variable, wrote every user of the ACL)
    assert viewscale(["credentials", "--out", str(tmp_path / "none"), "--users", ""]) == 2
    assert "user name ''" in capsys.readouterr().err and not (tmp_path / "none" / USERS_FILE).exists()
