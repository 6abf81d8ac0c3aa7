from __future__ import annotations

import pytest

from regtrack.pipeline.cache import MARKER, StageCache, file_digest, fingerprint


def test_fingerprint_changes_with_any_part():
    a = fingerprint({"c1": 0.54}, "abc")
    assert a == fingerprint({"c1": 0.54}, "abc")
    assert a != fingerprint({"c1": 0.55}, "abc")
    assert a != fingerprint({"c1": 0.54}, "abd")


def test_file_digest_of_file_and_folder(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "x.txt").write_text("1")
    d1 = file_digest(tmp_path / "d")
    (tmp_path / "d" / "x.txt").write_text("2")
    assert file_digest(tmp_path / "d") != d1
    assert len(file_digest(tmp_path / "d" / "x.txt")) == 64


def test_produce_is_atomic_and_counted(tmp_path):
    cache = StageCache(tmp_path)
    assert cache.lookup("mesh", "k1") is None
    with pytest.raises(RuntimeError):
        with cache.produce("mesh", "k1") as d:
            (d / "model.vtu").write_text("partial")
            raise RuntimeError("killed mid-stage")
    # nothing trusted, nothing left behind
    assert cache.lookup("mesh", "k1") is None
    assert list((tmp_path / "mesh").iterdir()) == []
    with cache.produce("mesh", "k1", info={"n": 1}) as d:
        (d / "model.vtu").write_text("done")
    hit = cache.lookup("mesh", "k1")
    assert hit is not None and (hit / "model.vtu").read_text() == "done" and (hit / MARKER).is_file()
    assert (cache.hits, cache.misses) == (1, 2)
    assert cache.marker("mesh", "k1")["info"] == {"n": 1}


def test_keys_follow_the_package_code(monkeypatch, tmp_path):
    """A change of regtrack's sources (a solver fix, same version) gives new stage keys, so
    a cached simulation of the old code is not re-used."""
    from regtrack.pipeline import cache as C

    k1 = fingerprint({"stage": "simulate"})
    assert k1 == fingerprint({"stage": "simulate"})
    monkeypatch.setattr(C, "code_digest", lambda: "another code")
    assert fingerprint({"stage": "simulate"}) != k1
