"""Light samplers: decompose a radiance map into a set of directional lights.

See ``base`` for the common types; one module per method (``pharr``, ``hemigon``, ``q2tree``,
``median_cut``) and ``peaks`` for strong-light detection.
"""
