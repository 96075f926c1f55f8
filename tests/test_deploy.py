"""``uma deploy certs`` / ``uma deploy config`` (:mod:`agent.deploy`): real certificates
checked with ``cryptography``, the access-control block, bad input named; and the SDK's
``zenoh_config=`` through a real TLS router on loopback."""

from __future__ import annotations

import json
import stat
import time
from pathlib import Path

import pytest
from agent_helpers.harness import START_WAIT_S, Proc, poll, spawn, uma_here
from conftest import free_port
from cryptography import x509
from cryptography.x509.oid import NameOID

from agent import Client, Service
from agent.deploy.certs import SiteSpec, create_site, load_site
from agent.deploy.zenoh_config import access_control, own_keys, write_configs
from agent.errors import UmaError
from agent.runtime.session import open_session

SPEC = SiteSpec(site="lab", router="r", hosts=["a", "b"], clients=["c"],
                addresses={"r": ["127.0.0.1", "router.lab"]})


def load(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_certs_are_signed_by_the_site_ca_and_name_their_host(tmp_path: Path) -> None:
    create_site(tmp_path, SPEC, days=10)
    ca = load(tmp_path / "ca" / "ca.pem")
    for name in ("r", "a", "b", "c"):
        host = tmp_path / "hosts" / name
        cert = load(host / "cert.pem")
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        assert (host / "ca.pem").read_bytes() == (tmp_path / "ca" / "ca.pem").read_bytes()
        assert stat.S_IMODE((host / "key.pem").stat().st_mode) == 0o600
    sans = load(tmp_path / "hosts/r/cert.pem").extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert [str(ip) for ip in sans.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert sans.get_values_for_type(x509.DNSName) == ["r", "router.lab"]
    assert stat.S_IMODE((tmp_path / "ca" / "ca.key").stat().st_mode) == 0o600
    assert load_site(tmp_path) == SPEC
    with pytest.raises(UmaError, match="exists already"):
        create_site(tmp_path, SPEC)


@pytest.mark.parametrize(("spec", "message"), [
    (SiteSpec("lab", "r", []), "at least one agent host"),
    (SiteSpec("lab", "r", ["a", "r"]), "named twice: r"),
    (SiteSpec("lab", "r", ["a/b"]), "host name 'a/b' is not valid"),
    (SiteSpec("lab", "r", ["a"], addresses={"x": ["1.2.3.4"]}), "unknown host"),
    (SiteSpec("lab", "r", ["a"], addresses={"a": ["not a name"]}), "neither an IP"),
])
def test_a_bad_site_is_named(spec: SiteSpec, message: str, tmp_path: Path) -> None:
    with pytest.raises(UmaError, match=message):
        create_site(tmp_path, spec)


def test_the_router_denies_by_default_and_each_host_writes_only_its_own_keys() -> None:
    acl = access_control(SPEC, "lab")
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["write-a"]["key_exprs"] == own_keys("lab", "a") == [
        "uma/lab/agent/a", "uma/lab/agent/a/**", "uma/lab/svc/a/**", "uma/lab/ctl/a/**",
        "uma/lab/data/a/**"]
    assert "put" not in rules["read"]["messages"]
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects["site"] == ["a", "b", "c"]  # the router itself never connects to itself
    assert "c" not in subjects["agent-hosts"]  # a client host writes nothing
    writes = [p for p in acl["policies"] if any(r.startswith("write-") for r in p["rules"])]
    assert {(p["rules"][0], p["subjects"][0]) for p in writes} == {
        ("write-a", "host-a"), ("write-b", "host-b")}


def test_config_writes_each_role_with_tls_only(tmp_path: Path) -> None:
    create_site(tmp_path, SPEC, days=10)
    written = write_configs(tmp_path, SPEC, "lab", ["tls/127.0.0.1:7447"],
                            ["tls/127.0.0.1:7447"], install_dir="/etc/uma")
    assert sorted(p.relative_to(tmp_path).as_posix() for p in written) == [
        "hosts/a/agent.json5", "hosts/a/client.json5", "hosts/a/service.json5",
        "hosts/b/agent.json5", "hosts/b/client.json5", "hosts/b/service.json5",
        "hosts/c/client.json5", "hosts/r/router.json5"]
    client = json.loads("".join(line for line in (tmp_path / "hosts/c/client.json5")
                                .read_text().splitlines(True) if not line.startswith("//")))
    tls = client["transport"]["link"]["tls"]
    assert client["transport"]["link"]["protocols"] == ["tls"]
    assert tls["connect_certificate"] == "/etc/uma/c/cert.pem" and tls["enable_mtls"]
    assert tls["verify_name_on_connect"]
    with pytest.raises(UmaError, match="TLS only"):
        write_configs(tmp_path, SPEC, "lab", ["tcp/127.0.0.1:7447"], ["tls/127.0.0.1:7447"])


def test_the_commands_explain_themselves_and_name_bad_input(tmp_path: Path) -> None:
    assert "one certificate per host" in uma_here("deploy", "--help").stdout
    assert "--router-endpoint" in uma_here("deploy", "config", "--help").stdout
    ok = uma_here("deploy", "certs", str(tmp_path), "--site", "lab", "--hosts", "a,b",
                  "--router", "r", "--address", "r=127.0.0.1")
    assert ok.returncode == 0 and "uma deploy config" in ok.stdout, ok.stderr
    ok = uma_here("deploy", "config", str(tmp_path), "--realm", "lab", "--router-endpoint",
                  "tls/127.0.0.1:7447")
    assert ok.returncode == 0 and "router.json5" in ok.stdout, ok.stderr
    for args, message in [
        (("certs", str(tmp_path), "--site", "lab", "--hosts", "a"), "exists already"),
        (("certs", str(tmp_path / "x"), "--site", "lab", "--hosts", ","), "comma-separated"),
        (("certs", str(tmp_path / "x"), "--site", "lab", "--hosts", "a", "--address", "r"),
         "NAME=ADDRESS"),
        (("config", str(tmp_path / "none"), "--realm", "lab", "--router-endpoint",
          "tls/127.0.0.1:7447"), "does not exist"),
        (("config", str(tmp_path), "--realm", "lab", "--router-endpoint",
          "tcp/127.0.0.1:7447"), "TLS only"),
    ]:
        out = uma_here("deploy", *args)
        assert out.returncode == 1 and message in out.stderr, (args, out.stderr)
    missing = uma_here("services", "--zenoh-config", str(tmp_path / "nope.json5"))
    assert missing.returncode == 1 and "does not exist" in missing.stderr


def test_service_and_client_take_a_zenoh_config(tmp_path: Path, processes, realm: str
                                                 ) -> None:
    port = free_port()
    router_ep = f"tls/127.0.0.1:{port}"
    spec = SiteSpec("lab", "r", ["hostA"], clients=["app"], addresses={"r": ["127.0.0.1"]})
    create_site(tmp_path, spec, days=1)
    write_configs(tmp_path, spec, realm, [router_ep], [router_ep])
    cfg = {name: str(tmp_path / "hosts" / name / f"{role}.json5")
           for name, role in (("r", "router"), ("hostA", "service"), ("app", "client"))}
    router = spawn(processes, ["-m", "agent.cli", "router", "--config", cfg["r"]])
    router.wait_line("listening on", START_WAIT_S)
    agent: Proc = spawn(processes, [
        "-m", "agent.cli", "agent", "--realm", realm, "--id", "hostA", "--connect", router_ep,
        "--mode", "client", "--zenoh-config",
        str(tmp_path / "hosts/hostA/agent.json5")])
    agent.wait_line("listening on", START_WAIT_S)
    with pytest.raises(UmaError, match="needs this host's certificates"):
        open_session("client", None, [router_ep])
    with Service("tracker", realm=realm, agent="hostA", connect=[router_ep],
                 zenoh_config=cfg["hostA"]) as svc:
        out = svc.ability("pose", type="pose6d", edge=("lab/world", "alice/head"),
                          frequency_hz=50)
        svc.start()
        with Client(realm=realm, connect=[router_ep], zenoh_config=cfg["app"]) as c:
            def pose() -> list[float]:
                out.publish(time.time_ns(), [0.5, 0.0, 1.5], [0, 0, 0, 1])
                return list(c.pose("lab/world", "alice/head").position)
            assert poll(pose, 60, "a pose over TLS") == pytest.approx([0.5, 0.0, 1.5])
