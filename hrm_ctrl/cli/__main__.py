import sys

from hrm_ctrl.cli import main

sys.exit(main())
