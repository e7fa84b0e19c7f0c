"""The camera-network experiment: simulated cameras detect and localize a moving target."""
