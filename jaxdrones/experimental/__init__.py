"""Experimental parts: built and checked against the rest of the package, not yet measured where they are meant to
pay, so no option, default or command-line flag reaches them. `pallas`: the control step as Pallas kernels."""
