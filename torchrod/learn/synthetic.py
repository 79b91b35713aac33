"""Another name for :mod:`torchrod.synthetic`'s load sets and streams, for code that imports them from here: the
same objects."""

from ..synthetic import *  # noqa: F403 (every public name, as the package lists it)
from ..synthetic import __all__ as __all__
