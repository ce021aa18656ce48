"""pipeline.util.heap.retained_heap: inside it a freed large array's pages are reused by the
next allocation (no new page faults), and on leaving the freed memory goes back to the system."""

from __future__ import annotations

import resource
import sys

import numpy as np
import psutil
import pytest

from pipeline.util import heap

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or heap._glibc() is None,
                                reason="glibc malloc only")
SIZE = 256 << 20  # bytes: far above malloc's largest mmap threshold (32 MiB)


@pytest.fixture(autouse=True)
def small_pages():
    """Page faults counted in 4 KiB pages: NumPy advises huge pages for large arrays otherwise
    (2 MiB per fault, and the kernel may or may not find them)."""
    old = np.core.multiarray._set_madvise_hugepage(False)
    yield
    np.core.multiarray._set_madvise_hugepage(old)


def _faults_writing_an_array() -> int:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.empty(SIZE, np.uint8)
    a[:] = 1
    after = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    del a
    return after - before


def test_freed_pages_are_reused_inside_and_returned_after() -> None:
    pages = SIZE // resource.getpagesize()
    assert _faults_writing_an_array() > pages // 2  # the plain allocator: a fresh mapping each time
    rss0 = psutil.Process().memory_info().rss
    with heap.retained_heap():
        _faults_writing_an_array()  # the heap grows once
        assert _faults_writing_an_array() < pages // 20  # then its pages serve the next array
    assert psutil.Process().memory_info().rss < rss0 + SIZE // 4  # malloc_trim gave them back
    assert _faults_writing_an_array() > pages // 2  # and the old limits are in force again


def test_the_switch_turns_it_off(monkeypatch) -> None:
    monkeypatch.setenv("FREPVDB_HEAP_RETAIN", "0")
    pages = SIZE // resource.getpagesize()
    with heap.retained_heap():
        _faults_writing_an_array()
        assert _faults_writing_an_array() > pages // 2
