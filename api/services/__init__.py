"""What the routes call: jobs and assets as the service sees them (lookups, checks, writes, submission).

Routes parse requests and shape answers; they import services, never each other.
"""
