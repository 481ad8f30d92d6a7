"""``python -m torchdem.cli_simulate`` = ``torchdem-simulate`` (for environments without the
console script on PATH, and for tests)."""
from torchdem.cli import simulate_main

if __name__ == "__main__":
    simulate_main()
