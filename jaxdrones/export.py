"""The former path of `jaxdrones.training.export` (a trained policy as one C file or ONNX): it keeps importing, as
that module."""

import sys

from jaxdrones.training import export as _export

sys.modules[__name__] = _export
