"""``python -m georefine``: the same command-line tool as ``georefine``."""

from georefine.cli import app

app(prog_name="georefine")
