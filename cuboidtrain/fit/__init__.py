"""The one pipeline a mask goes through: options, reading and framing, the networks' candidates, the cuboid fit, the choice (the Fitter)."""
