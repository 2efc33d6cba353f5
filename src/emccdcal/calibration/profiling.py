"""What a run costs before it runs: the likelihood's stages profiled on a few pixels (:class:`StageProfile`), and the fingerprint by which an interrupted run is resumed only with the same inputs."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import __version__
from .._util import progress as progress_bar
from ..errors import (
    InputError,
    MethodError,
    OptionError,
)
from ..model import noise
from .tiles import run_tile

if TYPE_CHECKING:
    pass


STAGE_GRID = (128, 181, 256, 362, 512, 724, 1024, 1448, 2048, 2896, 4096)
#: Pixels, the sensor's middle ones, on which the register's length is profiled.
PROFILE_PIXELS = 64


@dataclass(frozen=True)
class StageProfile:
    """The log-likelihood of the profiled pixels at each register length of
    :data:`STAGE_GRID` (``stages="auto"``), each pixel's other parameters fitted anew."""

    stages: tuple[int, ...]
    loglik: np.ndarray  # nats, summed over the pixels converged at every length
    pixels: int

    @property
    def best(self) -> int:
        """The register length of the largest likelihood."""
        return int(self.stages[int(np.argmax(self.loglik))])

    def attrs(self) -> dict:
        """The profile as a result's attributes: the grid, Δ log-likelihood (nats) and a
        sentence saying what was chosen, the lengths within 95 % (Δ > −1.92) and whether
        the data bound the length at all."""
        delta = self.loglik - self.loglik.max()
        within = [n for n, d in zip(self.stages, delta) if d > -1.92]
        source = (
            f"profile likelihood over {self.stages[0]}-{self.stages[-1]} stages on "
            f"{self.pixels} pixels: maximum at {self.best}, {min(within)}-{max(within)} "
            "within 95 %"
        )
        if max(within) == self.stages[-1]:
            source += " (no upper bound in the data: longer registers fit as well)"
        return {
            "register_stages_source": source,
            "register_stages_grid": np.array(self.stages, dtype=np.int64),
            "register_stages_profile": delta,
        }


def _profile_stages(tile_job, n_pixels, model, method, used, progress):
    """``(EMModel at the best length, StageProfile)``: the method fitted to the middle
    :data:`PROFILE_PIXELS` pixels at every length of :data:`STAGE_GRID`."""
    if not model.register.uses_stages:
        raise OptionError(
            f"stages='auto' profiles the cascade register's length; the {model} model has none"
        )
    if method.startswith("mv-"):
        raise MethodError(f"stages='auto' needs a likelihood: {method} has none")
    if all(a.em_gain_setpoint == 1 for a in used):
        raise OptionError(
            "stages='auto': every acquisition is at EM gain set-point 1, "
            "where the register's length does not enter the likelihood"
        )
    n = min(PROFILE_PIXELS, n_pixels)
    p0 = (n_pixels - n) // 2
    logliks = []
    for stages in progress_bar(
        STAGE_GRID, enabled=progress, desc="profiling register length", unit="length"
    ):
        job = replace(
            tile_job(p0, p0 + n, noise.EMModel(model.name, stages)), checks=False, intervals="wald"
        )
        logliks.append(run_tile(job)["loglik"])
    logliks = np.array(logliks)
    ok = np.all(np.isfinite(logliks), axis=0)
    if not ok.any():
        raise InputError(
            f"stages='auto': none of the {n} profiled pixels converged at every "
            f"register length ({STAGE_GRID[0]}-{STAGE_GRID[-1]}); give --stages N"
        )
    profile = StageProfile(STAGE_GRID, logliks[:, ok].sum(axis=1), int(ok.sum()))
    return noise.EMModel(model.name, profile.best), profile


def _fingerprint(
    manifest,
    used,
    method,
    options,
    intervals,
    checks,
    map_errors,
    phi_map,
    phi_se,
    tiling,
    em_model,
):
    """What a calibration's result depends on, to refuse resuming a different run."""
    files = {}
    paths = [manifest.path] + [a.frames_path for a in manifest.acquisitions]
    sources = [manifest.e_per_adu_source] + [
        s for a in manifest.acquisitions for s in (a.offset_source, a.read_noise_source)
    ]
    paths += [s.path for s in sources if s is not None and s.path is not None]
    for p in paths:
        st = Path(p).stat()
        files[str(Path(p).resolve())] = [st.st_size, st.st_mtime_ns]
    phi = None if phi_map is None else hashlib.sha256(np.ascontiguousarray(phi_map)).hexdigest()
    if phi_se is not None:
        phi += hashlib.sha256(np.ascontiguousarray(phi_se)).hexdigest()
    return {
        "emccdcal_version": __version__,
        "manifest_sha256": manifest.content_hash,
        "files": files,
        "method": method,
        "acquisitions": [a.name for a in used],
        "options": options,
        "intervals": intervals,
        "checks": bool(checks),
        "map_errors": bool(map_errors),
        "e_per_adu_sha256": phi,
        "blocks_and_tiles": [int(t) for t in tiling],
        "em_model": str(em_model),
    }
