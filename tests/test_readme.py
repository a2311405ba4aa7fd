"""The README's examples run as written."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_block(heading: str) -> str:
    text = README.read_text(encoding="utf-8")
    section = text.split(heading, 1)[1]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, f"no python block under {heading!r} in README.md"
    return match.group(1)


def test_library_example_runs_as_written(tmp_path, monkeypatch):
    (tmp_path / "scratch").mkdir()
    write_bundle(synth_avatar(gaussians=400, blendshapes=6, seed=2), tmp_path / "scratch" / "head.bundle")
    monkeypatch.chdir(tmp_path)
    code = _python_block("### Library")
    scope: dict = {}
    exec(compile(code, "README.md:Library", "exec"), scope)  # noqa: S102 - our own README
    out = scope["out"]
    assert out.rgb.shape == (4, 512, 512, 3) and out.alpha.shape == (4, 512, 512)
    assert torch.isfinite(out.rgb).all() and out.alpha.amax() > 0.5  # the avatar is in view


# What a shell example writes: --out, --workdir, --report, --contact-sheet, --trace, curl -o, tar's archive, and a
# shell redirection (not 2>, &>, <).
_WRITES = re.compile(r"(?:--out|--workdir|--report|--contact-sheet|--trace|-o|tar c\w*f)\s+(\S+)|(?<![<2&])>\s*(\S+)")


def test_shell_examples_write_only_under_ignored_folders():
    """A newcomer who runs the README's commands from the repository root leaves nothing untracked beside the
    sources: every file an example writes is under scratch/ (or the server's data/), both ignored by git; the
    upper-case names are placeholders and `adapter fit --out` names an adapter id, not a file."""
    import subprocess

    text = README.read_text(encoding="utf-8")
    written = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            code = "" if line.lstrip().startswith("#") else line.split(" # ")[0]
            for match in _WRITES.finditer(code):
                target = (match.group(1) or match.group(2)).rstrip(";")
                if target == "/dev/null" or re.fullmatch(r"[A-Z_]+", target) or (
                        "adapter fit" in code and "/" not in target):
                    continue
                written.append(target)
                assert target == "scratch" or target.startswith(("scratch/", "data/")), (
                    f"README example writes {target!r} outside scratch/: {code.strip()}")
    assert len(written) >= 10  # the examples were found
    root = README.parent
    ignored = subprocess.run(["git", "check-ignore", "scratch/x", "data/x"], cwd=root, capture_output=True, text=True)
    if ignored.returncode == 128:  # not a git checkout (an sdist): .gitignore still says it
        rules = (root / ".gitignore").read_text().split()
        assert "/scratch/" in rules and "/data/" in rules
    else:
        assert ignored.stdout.split() == ["scratch/x", "data/x"], ignored.stderr


def test_the_using_it_commands_run_verbatim_and_do_what_they_say(tmp_path):
    """The first shell block of "Using it", run as written from a checkout's root (the venv's commands, a scratch
    folder): every command exits 0, `bundle inspect` and the benchmarks print strict JSON, the bundle validates
    and the driving file renders one PNG per line."""
    import json
    import subprocess
    import sys

    text = README.read_text(encoding="utf-8")
    block = re.search(r"```bash\n(.*?)```", text.split("## Using it", 1)[1], re.S).group(1)
    (tmp_path / ".venv").symlink_to(Path(sys.executable).parents[1])
    run = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", block], cwd=tmp_path, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]

    def strict(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    decoder, docs, rest = json.JSONDecoder(parse_constant=strict), [], run.stdout.strip()
    while rest:
        doc, end = decoder.raw_decode(rest)
        docs.append(doc)
        rest = rest[end:].strip()
    manifest = next(d for d in docs if "expression_names" in d)
    assert len(manifest["expression_names"]) == 50 and manifest["precision"] == "fp16"
    benches = [d for d in docs if d.get("benchmark") == "render"]
    assert [b["backend"] for b in benches] == ["native", "reference"] and all(b["fps"] > 0 for b in benches)
    frames = sorted((tmp_path / "scratch" / "frames").glob("*.png"))
    assert len(frames) == 3, frames
    assert subprocess.run([str(tmp_path / ".venv" / "bin" / "blendsplat"), "bundle", "validate",
                           str(tmp_path / "scratch" / "head.bundle")], capture_output=True).returncode == 0


def test_the_test_command_is_ci_s_and_installs_the_client_package_first():
    """The README's test command is .ci/run's command line, character for character; it and the set-up command
    install ./clients/python (blendsplat-client, a dependency of the project that is not on PyPI) before the
    project, so pip never looks for it on the index."""
    text = README.read_text(encoding="utf-8")
    test_block = re.search(r"```bash\n(.*?)```", text.split("Run the tests", 1)[1], re.S).group(1).strip()
    ci = (README.parent / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()[-1]
    assert test_block == ci
    setup = re.search(r"```bash\n(.*?)```", text.split("## Set up and run", 1)[1], re.S).group(1).strip()
    for command, project in ((ci, "pip install -q -e '.[dev]'"), (setup, "pip install -e . ")):
        client = re.search(r"pip install (-q )?(-e )?\./clients/python\b", command)
        assert client and client.start() < command.index(project), command
