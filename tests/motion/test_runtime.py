"""The allocator setting used by the command line and the benchmarks."""

import platform
import subprocess
import sys


def test_retain_freed_memory_takes_effect_on_glibc_and_keeps_results_identical():
    """Run in a child process (the setting is process-wide): it reports success where glibc
    is the C library, and computations do not change."""
    code = (
        "import torch\n"
        "from motion.runtime import retain_freed_memory\n"
        "g = torch.Generator().manual_seed(0)\n"
        "x = torch.randn(3000, 3000, generator=g, dtype=torch.float64)\n"
        "before = (x @ x).sum().item()\n"
        "ok = retain_freed_memory()\n"
        "after = (x @ x).sum().item()\n"
        "print(ok, before == after)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    assert out == [str(glibc), "True"]
