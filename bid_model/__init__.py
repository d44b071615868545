"""The BID network, its data pipeline, training and closed-loop policy."""
