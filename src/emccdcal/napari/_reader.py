"""Camera stacks into napari, lazily, through emccdcal's readers."""

from __future__ import annotations

from pathlib import Path

__all__ = ["get_reader", "read", "stack_layer"]


def get_reader(path):
    """napari's reader hook: :func:`read` for one path (or a list) of a format emccdcal
    reads, None for anything else (napari then asks another reader)."""
    from ..data.stacks import STACK_SUFFIXES

    paths = [path] if isinstance(path, (str, Path)) else list(path)
    if not paths or not all(Path(p).suffix.lower() in STACK_SUFFIXES for p in paths):
        return None
    return read


def read(path) -> list[tuple]:
    """Layer data of each stack: ``(dask array (frames, rows, cols), {"name",
    "metadata"}, "image")``, nothing read until napari draws a frame."""
    paths = [path] if isinstance(path, (str, Path)) else list(path)
    return [stack_layer(Path(p)) for p in paths]


def stack_layer(path: Path) -> tuple:
    """One stack as napari layer data (its settings and path in the metadata)."""
    import dask.array as da

    from ..data.stacks import load_stack, stack_settings

    stack = load_stack(path)
    frames = da.from_array(
        stack, chunks=(1,) + tuple(stack.shape[1:]), asarray=True, name=f"emccdcal-{path}"
    )
    settings = stack_settings(path, setpoint_from_name=True)
    metadata = {"emccdcal_path": str(path), "units": "ADU (raw counts)", "camera": settings.known()}
    kwargs = {"name": path.name, "metadata": metadata}
    # where the file records its region of the sensor, the layer lies there (in sensor
    # pixels: a binned pixel spans its bins)
    if settings.roi is not None:
        bin_x, bin_y = settings.binning or (1, 1)
        kwargs.update(translate=(0, settings.roi[1], settings.roi[0]), scale=(1, bin_y, bin_x))
    return frames, kwargs, "image"
