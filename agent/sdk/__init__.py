"""Code that runs in a service's or a client's process: :class:`agent.Service`,
:class:`agent.Client`, the route planner and clock-offset estimation they use."""
