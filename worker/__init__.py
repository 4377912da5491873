"""Celery worker of the retargeting service: the only place that runs retarget_core for the service."""
