"""netkf_cli.core.llvm_pages: LLVM's clean pages are unmapped after each numba compilation, nothing else is, and
compiled code (old and new) still runs (issue 20's 300 MB)."""

import subprocess
import sys
import textwrap

import pytest

from netkf_cli.core.llvm_pages import _clean_regions

SMAPS = textwrap.dedent("""\
    7f0000000000-7f0000100000 r--p 00000000 08:01 42  /venv/llvmlite/binding/libllvmlite.so
    Rss:                 512 kB
    Anonymous:             0 kB
    7f0000100000-7f0000300000 r-xp 00100000 08:01 42  /venv/llvmlite/binding/libllvmlite.so
    Anonymous:             0 kB
    7f0000300000-7f0000310000 r--p 00300000 08:01 42  /venv/llvmlite/binding/libllvmlite.so
    Anonymous:            64 kB
    7f0000310000-7f0000320000 rw-p 00310000 08:01 42  /venv/llvmlite/binding/libllvmlite.so
    Anonymous:             0 kB
    7f0000400000-7f0000500000 r-xp 00000000 08:01 43  /usr/lib/libc.so.6
    Anonymous:             0 kB
    7f0000600000-7f0000700000 rw-p 00000000 00:00 0
    Anonymous:          1024 kB
    """)


def test_only_the_librarys_unwritten_read_only_mappings_are_released():
    """The header, the code: yes. The RELRO segment (copy-on-write pages the loader wrote), a writable mapping,
    another library, an anonymous mapping: no."""
    assert _clean_regions(SMAPS) == [(0x7F0000000000, 0x100000), (0x7F0000100000, 0x200000)]


def test_after_a_compilation_llvm_is_unmapped_and_compiled_code_still_runs():
    """In a fresh process: numba's import and a compilation map LLVM's code; once the compiler lock is released
    the library's clean mappings hold no resident page, the function compiled before and one compiled after
    give their values, and the writable mappings are untouched (the process would crash otherwise)."""
    pytest.importorskip("numba")
    if not sys.platform.startswith("linux"):
        pytest.skip("madvise on /proc/self/smaps regions: Linux only")
    code = textwrap.dedent("""
        import re
        from netkf_cli.linalg import kalman
        assert kalman.numba_available()
        import numba
        from netkf_cli.core import llvm_pages

        def resident():
            # kB resident in the library's released regions
            tot, cur = 0, False
            for line in open("/proc/self/smaps"):
                head = line.split(maxsplit=1)[0]
                if not head.endswith(":"):
                    lo = int(line.split("-")[0], 16)
                    cur = any(lo == r[0] for r in llvm_pages._regions)
                elif cur and head == "Rss:":
                    tot += int(line.split()[1])
            return tot

        f = numba.njit(lambda x: 2.0 * x + 1.0)
        assert f(1.5) == 4.0
        code_kb = sum(n for _, n in llvm_pages._regions) // 1024
        after_first = resident()
        g = numba.njit(lambda x, y: x * y - 3.0)
        assert g(2.0, 5.0) == 7.0 and f(2.0) == 5.0
        print(code_kb, after_first, resident())
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    code_kb, after_first, after_second = map(int, out.stdout.split())
    assert code_kb > 10_000, "the library's code mapping was not found (nothing would be released)"
    assert after_first == 0 and after_second == 0
