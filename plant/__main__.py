"""``python -m plant`` = ``hil-plant``."""

from plant.cli import main

raise SystemExit(main())
