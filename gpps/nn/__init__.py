"""The single-image network (seed 6.2.4): numpy inference of the shipped weights.

:mod:`gpps.nn.model` holds the architecture and the numpy forward pass (no PyTorch); it is a host
algorithm (same layer as :mod:`gpps.host`).  The random scenes the network was trained on, and the
training itself, live outside the package: ``training/shapes.py`` and ``training/train_single.py``.
"""
