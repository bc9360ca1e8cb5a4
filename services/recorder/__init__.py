"""The recorder service: session topics into one MCAP file per episode.

``service`` (the process), ``writer`` (file layout and crash bound), ``reader`` (``read_episode``),
``recover`` (partial files), ``validate`` (what counts as a malformed payload), ``control`` (the
client side of its control queryable: ``viewscale episode`` and the teleop devices' episode keys).
"""
