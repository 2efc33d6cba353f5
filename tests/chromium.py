"""Headless Chromium for the tests that open pages in a real browser (the HTML report,
the documentation site): where it is, the flags that keep it off the network, and one
call that runs it. Debian package ``chromium``; ``.ci/run`` installs it."""

from __future__ import annotations

import resource
import shutil
import subprocess

import pytest

CHROMIUM = next(
    (p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None
)
NOT_HERE = "no Chromium on this machine (Debian package 'chromium')"

# No background connections: this machine's network is closed, and they would fail.
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--mute-audio",
]


def _raise_address_space_limit():
    """Chromium reserves tens of GB of address space: lift a soft ``ulimit -v``."""
    hard = resource.getrlimit(resource.RLIMIT_AS)[1]
    resource.setrlimit(resource.RLIMIT_AS, (hard, hard))


def run(tmp_path, *args, timeout=120) -> str:
    """Run Chromium with ``args`` and a new profile in ``tmp_path``; its stdout."""
    profile = tmp_path / "chromium-profile"
    proc = subprocess.run(
        [CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        preexec_fn=_raise_address_space_limit,
    )
    hard = resource.getrlimit(resource.RLIMIT_AS)[1]
    if proc.returncode != 0 and hard != resource.RLIM_INFINITY:
        pytest.skip(
            f"Chromium failed under a hard address-space limit (ulimit -v {hard // 1024} "
            "KiB); it needs an unlimited one (set the limit with ulimit -S -v)"
        )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout
