"""Fields taken with the camera standing still: whole stacks (``sffscan stack``),
stop-and-go grids and the coarse prior of the two-step scan."""
