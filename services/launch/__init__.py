"""Starting a stack: ``zagv up`` (embedded router and supervised service processes), the standalone router,
systemd unit rendering, a whole stack in a subprocess for tests, benchmarks and scenarios (``stack_process``),
and the benchmarks of whole stacks."""
