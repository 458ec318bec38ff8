"""How much to trust a pose: features of a localization result and the calibrated model that
turns them into a confidence."""
