"""What the tests share that is not a test nor a fixture: helpers that test modules import,
and the suite's own pytest plugins. One module per job:

- environment: the test process's environment, before Django's settings (`-p` plugin)
- tiers: the suite's tiers and the guard on unmarked processes (`-p` plugin)
- hashers: the test process's fast password hasher (tests/conftest.py installs it)
- robot_setup: the test owners' password, RobotSetup and PairedRobot, seal_for
- anvil_rpc: anvil's test methods (snapshots, time, mining) and a chain's genesis
- chain_setup: an owner registered on the contract and an anchor item, without Django
- tampering: a stored envelope changed behind the portal's back
- logs: what a logger logs while a test runs
- harness: real Celery workers, beat, anvil and gunicorn for a test (WorkerStack)
- worker_robots: robots for tests with real workers, and one that keeps uploading
- anchoring_checks: every record anchored exactly once on the live chain
- fresh_python: a program run in a fresh interpreter
- source_imports: what the repository's modules import, read from the source
- screenshots: the browser tests' numbered screenshots and their folder
- layout: what the browser tests check of a page's layout
- access_log_data: access-log views made straight in the database
- agent_output: the agent's spool queue and the counters it logs
- custom_msgs: a robot's custom ROS 2 message type and a sample of it
- recordings: messages of known values, and ROS 1 and ROS 2 recordings of them
- records_server: a stand-in for the portal's records endpoint
- portal_checks: a robot's config for the live portal, and reading back what it stored

Import from the module that does the job; this package re-exports nothing.
"""
