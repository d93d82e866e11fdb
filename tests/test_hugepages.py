"""neld_jax.hugepages: when the entry points re-execute with glibc's huge-page tunable, and that they do it once."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from neld_jax import hugepages

ROOT = Path(__file__).resolve().parents[1]


def test_needs_reexec_only_where_it_can_help():
    assert hugepages.needs_reexec({}, (2, 36), "madvise")
    assert not hugepages.needs_reexec({}, (2, 34), "madvise"), "glibc < 2.35 has no such tunable"
    assert not hugepages.needs_reexec({}, None, "madvise"), "not glibc (musl, macOS)"
    assert not hugepages.needs_reexec({}, (2, 36), "always"), "every large mapping is huge already"
    assert not hugepages.needs_reexec({}, (2, 36), "never")
    assert not hugepages.needs_reexec({}, (2, 36), None)
    already = {"GLIBC_TUNABLES": "glibc.malloc.tcache_count=0:glibc.malloc.hugetlb=1"}
    assert not hugepages.needs_reexec(already, (2, 36), "madvise"), "set already: no loop"
    assert not hugepages.needs_reexec({"NELD_JAX_HUGEPAGES": "0"}, (2, 36), "madvise"), "opt-out"


def test_transparent_huge_page_mode_reads_the_bracketed_word(tmp_path):
    mode_file = tmp_path / "enabled"
    mode_file.write_text("always [madvise] never\n")
    assert hugepages.transparent_huge_page_mode(str(mode_file)) == "madvise"
    mode_file.write_text("garbage\n")
    assert hugepages.transparent_huge_page_mode(str(mode_file)) is None
    assert hugepages.transparent_huge_page_mode(str(tmp_path / "missing")) is None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc tunables exist on Linux only")
def test_a_script_reexecutes_once_with_the_tunable_and_keeps_its_arguments(tmp_path):
    """Run a script that calls the helper: it must finish with its arguments intact, and re-execute exactly
    once where the helper says it should (printing twice would mean no exec, or an exec loop)."""
    script = tmp_path / "entry.py"
    script.write_text(
        textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(ROOT)!r})
        print("start", os.environ.get("GLIBC_TUNABLES", ""), flush=True)
        from neld_jax.hugepages import reexec_with_huge_page_malloc
        reexec_with_huge_page_malloc()
        print("args", sys.argv[1:], flush=True)
    """)
    )
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", "NELD_JAX_HUGEPAGES")}
    result = subprocess.run(
        [sys.executable, "-u", str(script), "--x=1", "two words"], env=env, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    starts = [line for line in result.stdout.splitlines() if line.startswith("start")]
    expected = hugepages.needs_reexec(env, hugepages.glibc_version(), hugepages.transparent_huge_page_mode())
    assert len(starts) == (2 if expected else 1), result.stdout
    if expected:
        assert starts[1] == f"start {hugepages.TUNABLE}"
    assert result.stdout.splitlines()[-1] == "args ['--x=1', 'two words']"

    opted_out = subprocess.run(
        [sys.executable, str(script)], env=dict(env, NELD_JAX_HUGEPAGES="0"), capture_output=True, text=True, timeout=60
    )
    assert [line for line in opted_out.stdout.splitlines() if line.startswith("start")] == ["start "]
