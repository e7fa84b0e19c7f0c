"""The multi-process runtime over eclipse-zenoh: bus, agent, coordinator, router, launcher.

A thin shell around the algorithm core: every agent process runs
dqm.distributed (BalancedCore, CascadeCore), exactly as the in-process simulator does.
"""
