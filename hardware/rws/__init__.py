"""ABB Robot Web Services 1.0: shared names and joint targets (`protocol`), the Digest-auth HTTP client
(`client`) and a simulated IRC5 server (`sim`)."""
