import sys

from swarmplan.cli import main

sys.exit(main())
