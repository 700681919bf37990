"""The onboard agent of one vessel: its core (core/), its process (shell/), what every process shares (runtime/, config, contract, angles)."""
