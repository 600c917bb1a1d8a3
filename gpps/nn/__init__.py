"""The single-image network of issue 8 (seed 6.2.4): numpy inference of shipped weights, and its data recipe.

:mod:`gpps.nn.model` holds the architecture and the numpy forward pass (no PyTorch);
:mod:`gpps.nn.shapes` the random scenes the network was trained on. Training: ``training/train_single.py``.
"""
