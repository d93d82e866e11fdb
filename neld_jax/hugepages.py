"""Process set-up for the command-line entry points: glibc's malloc on transparent huge pages.

XLA:CPU allocates a step's temporary buffers afresh on every call (about 180 MB for the cpu budget's train
step) and glibc hands such large blocks back to the kernel when they are freed, so every step touches new
4 KiB pages. On the 2-core development VM that was ~44,000 minor page faults and ~150 ms of kernel time per
step, a third of the step's CPU time. glibc's tunable `glibc.malloc.hugetlb=1` makes malloc ask for
transparent huge pages (madvise), which cut the faults ~60-fold and the step's wall time by ~25%.

The tunable is read when the process starts, so an entry point calls `reexec_with_huge_page_malloc()` first
thing: the process replaces itself once with the same command line and the tunable set. Nothing happens
where it cannot help (not Linux/glibc >= 2.35, or transparent huge pages not in "madvise" mode), where the
tunable is already set, or with NELD_JAX_HUGEPAGES=0 in the environment.
"""

from __future__ import annotations

import os
import sys

TUNABLE = "glibc.malloc.hugetlb=1"
OPT_OUT = "NELD_JAX_HUGEPAGES"
THP_MODE_FILE = "/sys/kernel/mm/transparent_hugepage/enabled"


def glibc_version() -> tuple[int, int] | None:
    """(major, minor) of the running glibc, None if this is not glibc."""
    try:
        name, version = os.confstr("CS_GNU_LIBC_VERSION").split()
        major, minor = version.split(".")[:2]
        return (int(major), int(minor)) if name == "glibc" else None
    except (AttributeError, OSError, ValueError):
        return None


def transparent_huge_page_mode(path: str = THP_MODE_FILE) -> str | None:
    """The kernel's THP mode ("always", "madvise" or "never": the bracketed word), None if unknown."""
    try:
        with open(path) as f:
            text = f.read()
    except OSError:
        return None
    start, end = text.find("["), text.find("]")
    return text[start + 1 : end] if 0 <= start < end else None


def needs_reexec(environ: dict, libc: tuple[int, int] | None, thp_mode: str | None) -> bool:
    """Whether re-executing with TUNABLE would change anything (pure: the facts are arguments)."""
    if environ.get(OPT_OUT, "1") == "0" or "glibc.malloc.hugetlb" in environ.get("GLIBC_TUNABLES", ""):
        return False
    # "always": every large mapping is already huge; "never": the kernel gives none.
    return libc is not None and libc >= (2, 35) and thp_mode == "madvise"


def reexec_with_huge_page_malloc() -> None:
    """Replace this process with the same command line and glibc's huge-page tunable set (once); else return."""
    if not sys.platform.startswith("linux") or not needs_reexec(
        dict(os.environ), glibc_version(), transparent_huge_page_mode()
    ):
        return
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    env = dict(os.environ, GLIBC_TUNABLES=f"{tunables}:{TUNABLE}" if tunables else TUNABLE)
    sys.stdout.flush()
    sys.stderr.flush()
    # sys.orig_argv keeps the interpreter's own options (-u, -X ...) as well as the script and its arguments.
    os.execve(sys.executable, list(sys.orig_argv), env)
