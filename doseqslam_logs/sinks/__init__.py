"""Where outputs are written: files that appear whole or not at all (`atomic`), our message
types in each MCAP profile (`encoders`), and the annotated MCAP itself (`mcap_writer`)."""
