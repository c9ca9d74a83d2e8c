import sys

from occflownet.cli import main

sys.exit(main())
