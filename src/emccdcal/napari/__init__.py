"""The napari plugin (the ``napari`` extra): emccdcal where microscopists look at images.

An npe2 plugin (``napari.yaml`` beside this file, declared by the ``napari.manifest``
entry point), thin over the library:

- a reader: the camera stacks emccdcal reads (SPE, SIF, Micro-Manager/OME TIFF, FITS,
  Zarr, .npy) open lazily, one Dask array per stack, with the settings the file records
  in the layer's metadata (:mod:`._reader`);
- sample data: a simulated gain series (:mod:`._sample`);
- widgets (:mod:`._widgets`): calibrate a folder or manifest (what ``scan`` found, the
  method and register model, progress and cancel; the result as labelled layers, saved
  with its report), turn an image layer into photoelectrons (or photons) by a
  calibration, check the EM gain on dark frames, export a calibration to a localization
  tool's file.

Nothing here is imported by ``import emccdcal`` or the command line (napari and Qt are
not dependencies of the package); long work runs in a worker thread, so that the viewer
stays responsive. docs/napari.md shows it.
"""

from ._reader import get_reader

__all__ = ["get_reader"]
