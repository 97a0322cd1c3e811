"""Recording sessions to MCAP and replaying them."""
