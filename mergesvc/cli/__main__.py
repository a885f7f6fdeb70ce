"""`python -m mergesvc.cli ...` (how the tests and the demo start it)."""

from mergesvc.cli import main

main()
