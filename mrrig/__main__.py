"""`python -m mrrig` is the `mrrig` command."""

import sys

from mrrig.cli import main

sys.exit(main())
