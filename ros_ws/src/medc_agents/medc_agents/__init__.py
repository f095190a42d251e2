"""medc_agents."""
