import sys

from gcvd_flow.cli import main

sys.exit(main())
