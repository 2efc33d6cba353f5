"""Zarr stacks: a (frames, rows, cols) array, read by chunks (the ``zarr`` extra).

A store is an array, or an OME-Zarr image (OME-NGFF: a group whose ``multiscales``
attribute names its arrays; the first, full-resolution one is read, with axes
``t, y, x``). Zarr has no camera conventions; a store's settings are read from the
attribute ``"emccdcal"`` (of the array, else of the image's group), a mapping with the
field names of :class:`~emccdcal.data.settings.CameraSettings` (e.g.
``{"em_gain_setpoint": 300, "readout_rate_mhz": 10}``), else from the Micro-Manager
properties the group records under ``"micromanager"`` (``<camera>-<property>`` names, as
``emccdcal acquire`` writes them), which :func:`emccdcal.data.stacks.stack_settings`
returns.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import _files
from .._util import install_hint, one_line
from ..errors import InputError
from .settings import CameraSettings

__all__ = [
    "SUFFIXES",
    "ATTRIBUTE",
    "open_array",
    "header",
    "open_stack",
    "settings",
    "StackWriter",
    "Batch",
    "read_chunks",
    "begun_but_empty",
]

#: File name suffixes of this format.
SUFFIXES = (".zarr",)

#: The attribute holding a store's camera settings.
ATTRIBUTE = "emccdcal"


def open_array(path: Path):
    """The store's array, read-only and lazy (slicing reads only the chunks it touches)."""
    return _open(path)[0]


def _open(path: Path):
    """(the store's array, the attributes of the OME-Zarr group holding it, or {})."""
    try:
        import zarr
    except ImportError:
        raise InputError("reading Zarr needs the 'zarr' extra: " + install_hint("zarr")) from None
    try:
        node = zarr.open(str(path), mode="r")
    except Exception as exc:  # noqa: BLE001 - a damaged store can fail anywhere
        raise InputError(f"'{path}': not a Zarr array: {one_line(exc)}") from None
    if hasattr(node, "shape") and hasattr(node, "dtype"):
        return node, {}
    image = _image_path(node)
    if image is None:
        raise InputError(
            f"'{path}': a Zarr group that is not an OME-Zarr image; point at the stack's array"
        )
    try:
        return node[image], dict(node.attrs)
    except Exception as exc:  # noqa: BLE001 - a damaged store can fail anywhere
        raise InputError(
            f"'{path}': its OME-Zarr image '{image}' cannot be read: {one_line(exc)}"
        ) from None


def _image_path(group) -> str | None:
    """The full-resolution array of an OME-Zarr image group (NGFF 0.4, or 0.5's ``ome``)."""
    attrs = dict(group.attrs)
    scales = attrs.get("multiscales") or dict(attrs.get("ome") or {}).get("multiscales")
    try:
        return str(scales[0]["datasets"][0]["path"])
    except (TypeError, KeyError, IndexError):
        return None


def settings(path: Path) -> CameraSettings:
    """The settings recorded in the store's ``"emccdcal"`` attribute (unknown names are
    an error, so that a misspelt one is not silently dropped)."""
    arr, group = _open(path)
    recorded = arr.attrs.get(ATTRIBUTE) or group.get(ATTRIBUTE) or {}
    if not isinstance(recorded, dict):
        raise InputError(f"'{path}': its '{ATTRIBUTE}' attribute is not a table of settings")
    recorded = dict(recorded)
    if not recorded and isinstance(group.get("micromanager"), dict):
        from .micromanager import settings_of

        return settings_of(group["micromanager"])
    unknown = sorted(set(recorded) - set(CameraSettings.names()))
    if unknown:
        raise InputError(
            f"'{path}': unknown camera setting(s) {', '.join(unknown)} in its "
            f"'{ATTRIBUTE}' attribute (known: {', '.join(CameraSettings.names())})"
        )
    return CameraSettings.from_record(recorded, path)


def header(path: Path):
    """Shape, dtype, and no offset or stride: a store is read by chunks."""
    arr = open_array(path)
    return tuple(arr.shape), arr.dtype, None, None


open_stack = open_array


#: Bytes of one chunk of a stack (a batch of frames written at once).
_CHUNK_BYTES = 4 << 20
#: Rows of one chunk of a stack.
_CHUNK_ROWS = 64
#: Every chunk written as it is: zarr's test of a chunk for all-fill values (to skip it)
#: would cost a third of the writing, and a frame of zeros is data here.
_WRITE_CONFIG = {"write_empty_chunks": True}
#: What a Zarr store holds before its first chunk (formats 3 and 2).
_METADATA_FILES = {"zarr.json", ".zgroup", ".zarray", ".zattrs"}


# --------------------------------------------------------------------------------------
# Writing: an OME-Zarr image (NGFF 0.5, Zarr v3), frames appended in chunks
# --------------------------------------------------------------------------------------
class StackWriter:
    """An OME-Zarr image of (t, y, x) frames, appended a chunk at a time.

    The group's attributes hold the NGFF ``multiscales``, the camera settings
    (``emccdcal``: :class:`~emccdcal.data.settings.CameraSettings` fields) and every
    property the core reported (``micromanager``), which the project's Zarr reader reads.
    ``owner`` names the writer: the attribute that marks the stores it made (written with
    the group's first metadata), without which it resumes none. ``frames`` continues an
    earlier stack of that many frames (a resume): frames beyond them (a batch written
    when the run was killed) are dropped first.
    """

    def __init__(
        self, path: Path, shape, dtype, attrs: dict, *, owner: str, frames: int | None = None
    ):
        import zarr

        self.path = path
        h, w = shape
        self.chunk_frames = self.chunk_frames_of(shape, dtype)
        if frames is None:
            # the attributes (the session's marker among them) in the group's first and
            # only metadata write: zarr's attrs.update writes one key at a time, and a
            # run killed between two keys left a store that was no longer known as ours
            group = zarr.open_group(
                str(path),
                mode="w-",
                zarr_format=3,
                attributes={
                    "ome": {
                        "version": "0.5",
                        "multiscales": [
                            {
                                "name": path.name,
                                "axes": [
                                    {"name": "t", "type": "time"},
                                    {"name": "y", "type": "space"},
                                    {"name": "x", "type": "space"},
                                ],
                                "datasets": [
                                    {
                                        "path": "0",
                                        "coordinateTransformations": [
                                            {"type": "scale", "scale": [1.0, 1.0, 1.0]}
                                        ],
                                    }
                                ],
                            }
                        ],
                    },
                    owner: {},
                    **attrs,
                },
            )
            # chunks of a band of rows: calibrate reads a stack by bands of rows
            self.array = group.create_array(
                "0",
                shape=(0, h, w),
                dtype=dtype,
                chunks=(self.chunk_frames, min(h, _CHUNK_ROWS), w),
                compressors=None,
                fill_value=0,
                dimension_names=("t", "y", "x"),
                config=_WRITE_CONFIG,
            )
        else:  # a resume: only a stack this session wrote, only frames beyond its record
            try:
                group = zarr.open_group(str(path), mode="r+")
                ours = owner in group.attrs
                self.array = group["0"].with_config(_WRITE_CONFIG)
            except Exception:  # noqa: BLE001 - whatever is there, it is not our stack
                ours = False
            if not ours or self.array.shape[0] < frames:
                raise InputError(
                    f"'{path}': not the stack this session recorded (or "
                    f"fewer than its {frames} frames); it is left as it is"
                )
            if tuple(self.array.shape[1:]) != (h, w):
                raise InputError(
                    f"'{path}': frames of {self.array.shape[1]} × "
                    f"{self.array.shape[2]} px, but the camera gives {h} × {w}"
                )
            if self.array.shape[0] > frames:  # a batch written when the run was killed
                self.array.resize((frames, h, w))

    @staticmethod
    def chunk_frames_of(shape, dtype) -> int:
        """Frames of one chunk (about 4 MiB of a band of rows), at most 1024."""
        band = min(shape[0], _CHUNK_ROWS) * shape[1] * np.dtype(dtype).itemsize
        return int(min(1024, max(1, _CHUNK_BYTES // band)))

    @property
    def frames(self) -> int:
        return int(self.array.shape[0])

    def append(self, batch: Batch, count: int) -> None:
        """Append the first ``count`` frames of ``batch``.

        A batch of whole chunks is written as the chunks' files, then the array grown
        over them: a run killed in between leaves a stack of the frames before (never
        frames of fill values), and by Zarr v3 an uncompressed chunk is its C-order
        little-endian bytes. zarr's own asynchronous writing costs about a tenth of the
        camera's rate at 400 MB/s on two cores (benchmarks/bench_acquire.py); any other
        batch (a resume's first, the last) is written through zarr.
        """
        start, rest = self.frames, self.array.shape[1:]
        folder = self._chunk_folder()
        if folder is not None and count == self.chunk_frames and start % count == 0:
            for row, band in enumerate(batch.bands):
                path = folder / self.array.metadata.encode_chunk_key((start // count, row, 0))
                path.parent.mkdir(parents=True, exist_ok=True)
                with open(path, "wb") as fh:
                    fh.write(band)
            self.array.resize((start + count, *rest))
            return
        self.array.resize((start + count, *rest))
        for (top, bottom), band in zip(batch.rows, batch.bands):
            self.array[start : start + count, top:bottom] = band[:count, : bottom - top]

    def _chunk_folder(self) -> Path | None:
        """Where the array's chunk files are, if its chunks are plain little-endian bytes
        in a local store (else None: zarr writes them)."""
        import zarr

        array = self.array
        plain = (
            array.metadata.zarr_format == 3
            and array.dtype.str[0] in "<|"
            and array.metadata.codecs == (zarr.codecs.BytesCodec(endian="little"),)
        )
        store = array.store_path.store
        if not plain or not isinstance(store, zarr.storage.LocalStore):
            return None
        return Path(store.root) / array.path


class Batch:
    """Frames of one chunk's length kept as the stack's bands of rows: each band is then
    one whole chunk, which zarr writes as it is (a (frames, rows, cols) batch would be
    cut, filled and copied chunk by chunk: a third of the writing at 512 × 512 px). The
    last band is a whole chunk too, its rows below the frame zero (Zarr stores an edge
    chunk whole)."""

    def __init__(self, frames: int, shape, dtype):
        rows, cols = shape
        height = min(rows, _CHUNK_ROWS)
        self.rows = [(top, min(rows, top + height)) for top in range(0, rows, height)]
        self.bands = [np.zeros((frames, height, cols), dtype) for _ in self.rows]
        self.count = 0

    def add(self, frame: np.ndarray) -> None:
        for (top, bottom), band in zip(self.rows, self.bands):
            band[self.count, : bottom - top] = frame[top:bottom]
        self.count += 1

    def frames(self) -> np.ndarray:
        """The frames added, (count, rows, cols)."""
        return np.concatenate(
            [
                band[: self.count, : bottom - top]
                for (top, bottom), band in zip(self.rows, self.bands)
            ],
            axis=1,
        )


def read_chunks(path: Path, pixels=None):
    """A written stack's frames in chunks, (k, rows, cols), or of ``pixels`` only
    (flat indices), (k, 1, S)."""
    import zarr

    arr = zarr.open_group(str(path), mode="r")["0"]
    step = arr.chunks[0]
    for start in range(0, arr.shape[0], step):
        block = arr[start : start + step]
        yield block if pixels is None else block.reshape(block.shape[0], 1, -1)[:, :, pixels]


def begun_but_empty(path: Path, owner: str) -> bool:
    """Whether ``path`` is a store begun and never given a frame: a folder holding Zarr
    metadata only (a run killed while creating it, perhaps in the middle of a metadata
    write: zarr writes ``NAME.<id>.partial`` and renames it) and marked as ``owner``'s,
    so that nothing of a frame, and nothing of another's, is lost by making it again."""
    if not path.is_dir() or path.is_symlink():
        return False
    files = []
    for item in path.rglob("*"):
        if item.is_symlink():
            return False
        if item.is_file():
            files.append(item)
    if any(f.name not in _METADATA_FILES and not _metadata_in_writing(f) for f in files):
        return False
    root = path / "zarr.json"
    if root.is_file():  # the group's one metadata write carries its owner's marker
        return _marked(root, owner)
    # killed before the group's metadata was in place: folders only, or its write
    # interrupted (never Zarr v2's files: ours are v3)
    written = [f for f in files if f.parent == path and _metadata_in_writing(f)]
    return len(written) == len(files) and (not files or any(_marked(f, owner) for f in written))


def _metadata_in_writing(item: Path) -> bool:
    """A metadata file zarr was writing when the run was killed (``zarr.<id>.partial``)."""
    return item.name.startswith("zarr.") and item.name.endswith(".partial")


def _marked(item: Path, owner: str) -> bool:
    """Whether the Zarr metadata in ``item`` parses and carries ``owner``'s marker."""
    try:
        attrs = _files.load_json(item, what="Zarr metadata").get("attributes") or {}
    except (InputError, AttributeError):
        return False
    return owner in attrs  # else another hand's group (its attributes none or others)
