# The two commands of the README. Each installs missing Debian packages first.
.PHONY: run test build

run:
	tests/scripts/install-deps.sh build
	cargo run --release -p phone2act-cli --bin phone2act -- serve $(ARGS)

test:
	tests/scripts/test-all.sh

build:
	tests/scripts/install-deps.sh build
	cargo build --workspace --all-targets
