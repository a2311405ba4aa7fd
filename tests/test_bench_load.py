"""`blendsplat bench load`: cold and warm loads from a temporary store, each in a fresh process."""

from __future__ import annotations

import json

import pytest

from render_core.bundle import write_bundle
from render_core.errors import BundleError
from render_core.tools.synth import synth_avatar
from service.bench_load import bench_load
from service.cli import main


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    path = tmp_path_factory.mktemp("bench-load") / "a.bundle"
    write_bundle(synth_avatar(gaussians=300, blendshapes=4, seed=5), path)
    return path


def test_bench_load_reports_cold_and_warm_stages_memory_and_verification(bundle, tmp_path, monkeypatch):
    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the temporary store goes here, so we can see it is removed
    r = bench_load(bundle, size=32)
    assert (r["benchmark"], r["schema_version"], r["gaussians"], r["size"]) == ("load", 2, 300, 32)
    assert r["file_bytes"] == bundle.stat().st_size and r["resident_bytes"] > 0 and r["verify_ms"] > 0
    assert r["resident_fresh_process_bytes"] > 0 and r["verified_on_load"] is False  # the store's record trusted
    for key in ("cold_ms", "warm_ms"):
        ms = r[key]
        assert set(ms) == {"read", "renderer", "first_frame", "total"} and min(ms.values()) > 0
        assert ms["total"] >= ms["read"] + ms["renderer"]  # the total spans the stages and the frame
    assert list(tmp_path.iterdir()) == []  # the temporary store is gone


def test_bench_load_command_prints_one_json_line_and_refuses_a_broken_bundle(bundle, tmp_path, capsys):
    assert main(["bench", "load", "--bundle", str(bundle), "--size", "16", "--json"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and json.loads(out)["cold_ms"]["total"] > 0
    broken = tmp_path / "broken.bundle"
    broken.write_bytes(bundle.read_bytes()[:-100])
    with pytest.raises(BundleError):
        bench_load(broken, size=16)
    assert main(["bench", "load", "--bundle", str(broken)]) == 1
    assert "blendsplat: error:" in capsys.readouterr().err


def test_bench_load_vs_v1_reports_the_same_avatar_as_a_dense_schema_1_file(tmp_path, monkeypatch):
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    (tmp_path / "keep").mkdir()
    path = tmp_path / "keep" / "local.bundle"  # compact blendshapes (as a face model's): most pairs are zero
    write_bundle(synth_avatar(gaussians=400, blendshapes=6, seed=2, local=True), path)
    r = bench_load(path, size=24, vs_v1=True)
    old = r["v1"]
    assert (r["schema_version"], old["schema_version"]) == (2, 1)
    assert old["gaussians"] == r["gaussians"] and old["precision"] == r["precision"]
    assert old["file_bytes"] > r["file_bytes"]  # dense: every pair stored
    assert r["v1_over_this"]["file_bytes"] == round(old["file_bytes"] / r["file_bytes"], 2)
    assert set(old["cold_ms"]) == {"read", "renderer", "first_frame", "total"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep"]  # both temporary stores are gone


def test_bench_load_vs_v1_of_an_int8_bundle_compares_with_a_dense_fp16_file(tmp_path):
    """Schema 1 has no int8: the dense comparison is stored in fp16 instead of failing on the precision."""
    path = tmp_path / "int8.bundle"
    write_bundle(synth_avatar(gaussians=300, blendshapes=4, seed=3), path, precision="int8")
    r = bench_load(path, size=16, vs_v1=True)
    assert (r["precision"], r["v1"]["precision"], r["v1"]["schema_version"]) == ("int8", "fp16", 1)
