"""deploy/*.json5 are what dqm's own commands configure: zenoh parses every file, and each
setting dqm relies on equals the one `dqm router` / `dqm agent` build from their options."""
import argparse
import json
from pathlib import Path

import pytest

from dqm.commands.runtime_options import tls_from
from dqm.runtime.bus import client_config, router_config

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
CERTS = "/etc/dqm/certs"
KEYS = ["mode", "scouting/multicast/enabled", "scouting/gossip/enabled", "transport/shared_memory/enabled",
        "transport/link/tls"]


def _tls(name):
    return argparse.Namespace(tls_ca=f"{CERTS}/ca.pem", tls_cert=f"{CERTS}/{name}.pem", tls_key=f"{CERTS}/{name}.key")


def _no_tls():
    return argparse.Namespace(tls_ca=None, tls_cert=None, tls_key=None)


CASES = {
    "router-tcp.json5": lambda: router_config(["tcp/0.0.0.0:7447"], tls_from(_no_tls(), listen=True)),
    "router-mtls.json5": lambda: router_config(["tls/0.0.0.0:7448"],
                                               tls_from(_tls("router"), listen=True, check_files=False)),
    "agent-tcp.json5": lambda: client_config("tcp/192.0.2.10:7447", tls_from(_no_tls(), listen=False)),
    "agent-mtls.json5": lambda: client_config("tls/192.0.2.10:7448",
                                              tls_from(_tls("agent0"), listen=False, check_files=False)),
}


def test_every_deploy_config_is_covered():
    assert sorted(p.name for p in DEPLOY.glob("*.json5")) == sorted(CASES)


@pytest.mark.parametrize("name", sorted(CASES))
def test_deploy_config_equals_what_dqm_builds(name):
    import zenoh

    file_cfg = zenoh.Config.from_file(str(DEPLOY / name))
    dqm_cfg = CASES[name]()
    ends = "listen/endpoints" if name.startswith("router") else "connect/endpoints"
    for key in KEYS + [ends]:
        assert json.loads(file_cfg.get_json(key)) == json.loads(dqm_cfg.get_json(key)), key
    assert json.loads(file_cfg.get_json("transport/shared_memory/enabled")) is False
