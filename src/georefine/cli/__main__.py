"""``python -m georefine.cli``."""

from georefine.cli import app

app(prog_name="georefine")
