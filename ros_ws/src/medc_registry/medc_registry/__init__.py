"""medc_registry."""
