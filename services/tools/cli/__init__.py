"""`telerobot`: one command for the router, the launcher, every service and introspection.

`main` (the command and its subcommands), `launcher` (`telerobot up PROFILE`: a profile's
services as child processes), `demo` (`telerobot demo`: the whole system in simulation
with the console), `bench` (`telerobot bench`'s command line), `introspect` (`topic
list|echo|hz`, `call`, `alive`, in the spirit of the ros2 CLI).
"""
