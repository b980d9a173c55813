"""The physics: scenes, the ``Cloth`` facade over the native engine, the stability bound and
the NumPy float64 oracle. Imports nothing of the package but the native module."""
