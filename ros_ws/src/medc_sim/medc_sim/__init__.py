"""medc_sim."""
