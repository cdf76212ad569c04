"""mrrig's shipped configs, the CAN contract's DBC, the Zenoh templates and the test plans: the
package data `mrrig.configs` (`mrrig/configs` is a link to this folder, which stays the one
editable copy). Found through `mrrig.resources`, never by a path computed from a checkout."""
