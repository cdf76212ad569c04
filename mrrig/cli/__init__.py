"""The `mrrig` command (`main`) and the front ends of the operator's subcommands."""
