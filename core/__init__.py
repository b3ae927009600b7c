"""Infrastructure the apps share and that knows nothing of them: secret files, the Redis
client, the outbox that queues tasks by name, the mapping from domain errors to HTTP."""
