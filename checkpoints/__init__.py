"""The warm-start networks that install with torchrod, as ``torchrod.checkpoints``: ``nitinol290.pt``, trained for
the ``nitinol290`` grating layout (``torchrod.data.path("nitinol290.pt")`` finds it wherever torchrod is installed).

``torchrod train`` writes its network to ``checkpoints/warm_start.pt`` under the folder it runs in (here, when run
from the repository's root); only the networks named in ``pyproject.toml``'s package data install with torchrod.
"""
