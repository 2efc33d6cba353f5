"""The camera's noise model: :mod:`~emccdcal.model.noise` (the exact pmf of the counts,
gamma EM register), :mod:`~emccdcal.model.cascade` (the exact Bernoulli-cascade
register) and :mod:`~emccdcal.model.psf` (the pixel-integrated Gaussian spot).

A register model is a subclass of :class:`Register` (:mod:`.register`: it supplies the
transform of one electron's output and inherits the rest), or any class with the members
of :class:`RegisterModel`, whose rows have those of :class:`RegisterRows`
(:mod:`._protocol`); the models known by name are :data:`emccdcal.model.noise.EM_MODELS`."""

from .._lazy import submodules as _submodules

from ._protocol import RegisterModel, RegisterRows
from .register import Register

__all__ = ["Register", "RegisterModel", "RegisterRows"]

# its modules as attributes, imported on first use (as after `import emccdcal`)
__getattr__, __dir__ = _submodules(__name__, __path__)
