"""The simulated indoor world: room generator, RGB-D renderer, ground truth, mock autopilot."""
