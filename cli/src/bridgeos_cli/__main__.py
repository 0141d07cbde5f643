"""`python -m bridgeos_cli`: the same as the `bridgeos` console script."""

from bridgeos_cli.main import main

main()
