"""``lj.keep_freed_memory``: a compiled program's temporaries stop being mapped afresh at every call.

The allocator is a setting of the whole process, so the check runs in a child process of its own,
on the allocation pattern of a compiled program's call: one block above glibc's largest mmap
threshold (32 MiB), written and freed. Without the setting each such block is mapped anew and
its pages touched for the first time (a minor page fault per 4 KiB page); with it the next block
reuses the freed one's pages; ``keep_freed_memory(False)`` brings the faults back. (An XLA
program's temporaries behaved so at XLA's default code generation, but not reliably under the
suite's compile flags, which allocate them otherwise: ``scripts/bench.py --only default_call``
measures a gradient's faults with and without the setting.)
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import ldap_jax as lj
from ldap_jax._allocator import _libc

CHILD = r"""
import ctypes, json, resource, sys
import ldap_jax as lj

libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
libc.memset.restype, libc.memset.argtypes = ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t]
SIZE = 40 << 20  # a compiled program's temporaries: one block, above glibc's mmap ceiling


def faults(calls):
    out = []
    for _ in range(calls):
        a = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        block = libc.malloc(SIZE)
        libc.memset(block, 1, SIZE)
        libc.free(block)
        out.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - a)
    return out


plain = faults(4)
kept = lj.keep_freed_memory()
during = faults(4)
released = lj.keep_freed_memory(False)
after = faults(4)
json.dump(dict(pages=SIZE // 4096, flags=[kept, released], plain=plain, during=during, after=after),
          open(sys.argv[1], "w"))
"""


@pytest.mark.skipif(
    _libc() is None, reason="the setting applies to glibc's allocator only (elsewhere it returns False)"
)
def test_kept_memory_is_not_touched_afresh_at_every_call(tmp_path):
    out = tmp_path / "faults.json"
    subprocess.run([sys.executable, "-c", CHILD, str(out)], check=True, timeout=300)
    r = json.loads(out.read_text())
    pages = r["pages"]
    assert r["flags"] == [True, True], r
    # glibc as it is: every block mapped anew and its pages touched for the first time
    assert min(r["plain"]) >= 0.9 * pages, r
    # kept: the block freed by one call is the next call's (the kernel may reclaim idle kept
    # pages on some machines, so the best of the calls after the first is asserted)
    assert min(r["during"][1:]) <= 0.05 * pages, r
    # released again: mapped anew at every call
    assert min(r["after"]) >= 0.9 * pages, r


def test_keep_freed_memory_names_a_bad_argument():
    with pytest.raises(TypeError, match="'keep'"):
        lj.keep_freed_memory("yes")
