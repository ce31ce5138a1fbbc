"""The event simulator: scenes, exact motions, presets and the out-of-the-box examples."""
