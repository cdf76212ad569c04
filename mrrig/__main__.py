"""`python -m mrrig` is the `mrrig` command."""

import sys

from mrrig.cli.main import main

sys.exit(main())
