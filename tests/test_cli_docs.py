"""What the command says about itself agrees with README: run's options, its outputs, and
the closing hint of ``demo`` and ``run``, which must work without activating the environment."""

import fnmatch
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from reconstruct.cli.parser import RUN_EPILOG, build_parser

ROOT = Path(__file__).resolve().parents[1]


def _readme_section(title: str) -> str:
    return (ROOT / "README.md").read_text().split(title, 1)[1].split("\n## ", 1)[0]


def _run_parser():
    parser = build_parser()
    return parser._subparsers._group_actions[0].choices["run"]


def test_readme_options_table_lists_every_run_option():
    table = [row for row in _readme_section("## Reconstructing a capture").splitlines() if row.startswith("| `-")]
    documented = {flag for row in table for flag in re.findall(r"`(--?[a-z][a-z-]*)", row.split(" | ")[0])}
    options = {flag for action in _run_parser()._actions for flag in action.option_strings} - {"-h", "--help"}
    # -o is the command's argument, shown in the example above the table.
    assert options - documented - {"-o", "--output"} == set()
    assert documented - options == set()
    rows = [row.split(" | ")[0] for row in table]
    assert len(rows) == len(set(rows)) and sum("--normals" in r for r in rows) == 1


def _epilog_files() -> set[str]:
    outputs = RUN_EPILOG.split("outputs", 1)[1].split("example:", 1)[0]
    return set(re.findall(r"(?<![\w-])(?:[\w*]+\.[a-z]{2,4}|[a-z]+/)(?=[\s,)]|$)", outputs))


def test_run_help_lists_the_output_folder_as_readme_does():
    from reconstruct.pipeline.compare_run import COMPARISON_FILES

    table = _readme_section("## Output folder")
    documented = {n for row in table.splitlines() if row.startswith("| `")
                  for n in re.findall(r"`([^`]+)`", row.split("|")[1])}
    listed = _epilog_files() - {"README.md"}
    expected = documented | set(COMPARISON_FILES)
    # The help may name a family of files by a pattern (loo_*.tif).
    assert {n for n in expected if not any(fnmatch.fnmatchcase(n, p) for p in listed)} == set()
    assert {p for p in listed if not any(fnmatch.fnmatchcase(n, p) for n in expected)} == set()
    help_text = _run_parser().format_help()
    assert all(name in help_text for name in listed)


@pytest.mark.parametrize("how", ["script", "module"])
def test_demo_hint_runs_without_activating_the_environment(tmp_path, how):
    """The closing hint (``… preview OUT``) names this environment's command, so it runs from a
    shell where the environment is not activated."""
    script = Path(sys.executable).with_name("reconstruct")
    if how == "script" and not script.is_file():
        pytest.skip("the reconstruct script is not installed beside this interpreter")
    start = [str(script)] if how == "script" else [sys.executable, "-m", "reconstruct"]
    bare = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    bare["PATH"] = "/usr/bin:/bin"
    done = subprocess.run([*start, "demo", "-o", str(tmp_path / "demo"), "--size", "64x48", "--lights", "8"],
                          env=bare, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    hint = re.search(r"look at it in 3D: (.*)$", done.stdout, re.MULTILINE).group(1)
    words = shlex.split(hint)
    assert words[-2:] == ["preview", str(tmp_path / "demo" / "result")]
    assert words[:-2] == ([str(script)] if how == "script" else [sys.executable, "-m", "reconstruct"])
    again = subprocess.run([*words[:-2], "--version"], env=bare, cwd="/", capture_output=True, text=True,
                           timeout=120)
    assert again.returncode == 0 and "reconstruct" in again.stdout, again.stderr
