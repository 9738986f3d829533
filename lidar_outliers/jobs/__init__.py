"""What the job service's API and its workers share: settings, the job store, the job-folder
layout, the queue's configuration and the run of one job (callable without Celery)."""
