"""service.heap: the heap's free pages go back to the system (glibc), so RSS shows what is used."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_free_heap_pages_leave_the_rss() -> None:
    # In a fresh process: 200 MB in 64 kB blocks (below glibc's mmap threshold: from the heap),
    # all freed but the last (which pins the heap's top, so free() alone cannot shrink it).
    code = textwrap.dedent(
        """
        def rss_mb():
            for line in open("/proc/self/status"):
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        from wristscan.daemon.service.heap import release_free_heap
        base = rss_mb()
        blocks = [bytearray(b"x" * 65536) for _ in range(3200)]
        last = blocks[-1]
        del blocks[:-1]
        held = rss_mb() - base
        assert release_free_heap()
        print(f"{held:.1f} {rss_mb() - base:.1f} {len(last)}")
        """
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    held, after, _ = (float(v) for v in res.stdout.split())
    assert held > 150, held  # free() kept the pages
    assert after < 30, after  # malloc_trim gave them back
