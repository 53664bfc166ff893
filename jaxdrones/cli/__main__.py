"""``python -m jaxdrones.cli ...``: the ``jaxdrones`` command."""

from jaxdrones.cli import run

run()
