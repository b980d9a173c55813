"""The shared protocol vectors (tests/data/protocol_vectors.json) are current: they decode
in Python to what the file says, and regenerating them from today's encoder gives the same
messages. The browser side of the same file is checked in test_web_browser.py."""

from __future__ import annotations

import base64
import json

import pytest
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay

from tests.web.web_vectors import VECTORS, build, expectation


@pytest.fixture(scope="module")
def stored() -> dict:
    return json.loads(VECTORS.read_text())


def test_every_stored_message_decodes_in_python_as_stored(stored: dict) -> None:
    assert stored["protocol_version"] == P.PROTOCOL_VERSION
    kinds = set()
    errors = set()
    for v in stored["binary"]:
        data = base64.b64decode(v["b64"])
        assert expectation(data) == v["expect"], v["name"]
        kinds.add(v["expect"].get("kind"))
        errors.add(v["expect"].get("error"))
    # the file covers every message type, both mesh encodings, and refusals
    assert {"HIP", "CORNER", "MESH", "TRACK"} <= kinds
    flags = {v["expect"]["flags"] for v in stored["binary"] if v["expect"].get("kind") == "MESH"}
    assert flags == {0, P.FLAG_ZLIB | P.FLAG_DELTA}
    versions = {v["expect"]["version"] for v in stored["binary"]
                if v["expect"].get("kind") == "MESH"}
    assert versions == {1, P.MESH_VERSION}  # old replays' MESH and today's
    assert {"bad_binary", "bad_version"} <= errors


def test_the_file_is_what_todays_encoder_makes(stored: dict) -> None:
    fresh = build()
    assert [v["name"] for v in fresh["binary"]] == [v["name"] for v in stored["binary"]], (
        "vectors out of date: run `python tests/web_vectors.py`"
    )
    for new, old in zip(fresh["binary"], stored["binary"], strict=True):
        assert new["expect"] == old["expect"], (
            f"{new['name']}: the encoder changed; run `python tests/web_vectors.py`"
        )
        if new["expect"].get("flags", 0) & P.FLAG_ZLIB:
            continue  # zlib's bytes may differ between zlib builds; the decoded values agree
        assert new["b64"] == old["b64"], f"{new['name']}: bytes differ from the stored vector"
    assert fresh["replay"]["header"] == stored["replay"]["header"]
    assert fresh["replay"]["records"] == stored["replay"]["records"]
    assert fresh["replay_v1"] == stored["replay_v1"]


def test_replay_vector_reads_as_stored(stored: dict) -> None:
    rv = stored["replay"]
    header, records = read_replay(base64.b64decode(rv["b64"]))
    assert header == rv["header"]
    assert len(records) == len(rv["records"])
    for (kind, data), want in zip(records, rv["records"], strict=True):
        assert kind == want["record"]
        if kind == 0:
            assert json.loads(data) == want["json"]
        else:
            assert {"record": 1, **expectation(data)} == want
