"""``python -m torchrod.data [NAME]``: the files torchrod ships, or the path of one (see :mod:`torchrod.data`)."""

from . import main

raise SystemExit(main())
