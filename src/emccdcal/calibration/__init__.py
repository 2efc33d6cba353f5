"""The main job: a manifest in, a labelled calibration out (``emccdcal calibrate``).

The sensor is processed in tiles of whole blocks of pixels (:func:`plan_tiles`). A tile
reads only the rows that hold its pixels, of every acquisition, once, into per-pixel histograms
(:mod:`emccdcal.data.stats`) and the statistics of the data-quality checks
(:class:`emccdcal.data.quality.StackSummary`); fits its pixels with the likelihood engine
(:mod:`emccdcal.fit.engine`) driven by the method's layout (:mod:`emccdcal.fit.layouts`),
in blocks on threads; and is kept (:class:`emccdcal.runstore.RunStore`) before the next
one is read. Peak memory is set by the tile, not by the sensor, and an interrupted run
can be resumed. Tiles run here or as tasks on a Dask cluster (:func:`run_tile` is all a
worker executes). At the end the tiles are assembled into one labelled result
(:mod:`emccdcal.result`) and the data-quality checks are judged.
"""

from ..defaults import DEFAULT_BLOCK, DEFAULT_TILE_PIXELS, INTERVALS, METHODS
from .api import calibrate
from .profiling import STAGE_GRID, StageProfile
from .summary import format_summary
from .tiles import TileJob, plan_tiles, run_tile

__all__ = [
    "METHODS",
    "INTERVALS",
    "DEFAULT_BLOCK",
    "DEFAULT_TILE_PIXELS",
    "TileJob",
    "calibrate",
    "plan_tiles",
    "run_tile",
    "format_summary",
    "STAGE_GRID",
    "StageProfile",
]
