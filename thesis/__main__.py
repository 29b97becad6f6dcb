"""`python -m thesis`: the same as `python -m thesis.reproduce`."""

from thesis.reproduce import main

raise SystemExit(main())
