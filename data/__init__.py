# torchrod.data: this folder installs as the package torchrod.data (pyproject.toml's package-dir), the rod files and
# example data beside this file, the network in checkpoints/ (torchrod.checkpoints). Its code and documentation are
# torchrod/shipped.py, so that they are checked and documented with the rest of the package.
from torchrod.shipped import FILES, path
from torchrod.shipped import __doc__ as __doc__
from torchrod.shipped import main as main  # python -m torchrod.data

__all__ = ["FILES", "path"]
