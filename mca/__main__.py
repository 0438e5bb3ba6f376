"""`python -m mca`: the same command line as the `mca` script."""

from mca.capture.cli import main

main()
