"""Every shipped campaign store (campaigns/manifest.json) opens with the config of its command.

A store refuses a config whose result-deciding blocks hash differently from the one it was
created with; a new key in a shared config file (``conf/geometry/drawdown_full.yaml`` ...)
changes that hash for every store whose geometry inherits it. This test recomposes each store's
command and compares hashes, so such a change fails here instead of on a user's resume.
"""
import json
import sqlite3
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from bo.cli.common import MODEL_KEYS, plain_config, store_hashes
from torchdem.cli import CONF_DIR

CAMPAIGNS = Path(__file__).resolve().parent.parent / "campaigns"
MANIFEST = json.loads((CAMPAIGNS / "manifest.json").read_text())


@pytest.mark.parametrize("entry", MANIFEST["stores"], ids=lambda e: e["store"])
def test_shipped_store_matches_its_command_config(entry):
    path = CAMPAIGNS / entry["store"]
    if not path.exists():
        pytest.skip(f"{path.name} not created yet")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose(entry["config"], overrides=entry["overrides"]))
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as conn:
        stored = dict(conn.execute("SELECT key, value FROM meta").fetchall())["config_hash"]
    hashes = store_hashes(plain, MODEL_KEYS + tuple(entry.get("hashed_also", ())))
    assert stored in hashes, f"{entry['store']}: the config of `{entry['command']}` changed"


def test_every_shipped_store_is_in_the_manifest():
    listed = {e["store"] for e in MANIFEST["stores"]}
    assert {p.relative_to(CAMPAIGNS).as_posix() for p in CAMPAIGNS.rglob("*.sqlite")} <= listed
