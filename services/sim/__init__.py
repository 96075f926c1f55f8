"""The simulated world: IVY six-sided display, head trajectory and ground truth."""
