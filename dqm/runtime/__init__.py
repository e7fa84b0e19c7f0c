"""The multi-process runtime over eclipse-zenoh: bus, agent, coordinator, router, launcher.

A thin shell around the algorithm core: every agent process runs
dqm.core.distributed.AgentCore, exactly as the in-process simulator does.
"""
