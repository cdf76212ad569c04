"""Test plans (`mrrig test`): a plan's steps parsed once (`plan`), each step's numbers and
verdict (`criteria`, numerics), the steps run on a live rig through its public interfaces
(`runner`), and the reports (`report`: JUnit XML, HTML)."""
