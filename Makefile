# conformd — `make demo` runs the main job on built-in defaults, `make test` runs every
# test. Both first install the system packages the build needs when they are missing.

APT_PACKAGES := libopencv-dev clang libclang-dev pkg-config libudev-dev
CARGO ?= cargo
DEMO_OUT ?= demo-output

.PHONY: all deps build lint test demo bench clean

all: build

# System packages through apt-get (sudo when not root); the Rust toolchain must exist.
deps:
	@missing=""; \
	for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing >/dev/null; \
	fi
	@command -v $(CARGO) >/dev/null || { echo "cargo is not installed: install the Rust toolchain with rustup"; exit 1; }

build: deps
	$(CARGO) build --locked --release

# Formatting and clippy (warnings are errors), on the same profile as the tests so the
# dependencies are checked once.
lint: deps
	$(CARGO) fmt --check
	$(CARGO) clippy --locked --profile ci --all-targets -- -D warnings

# Lint, then every test, compiled once: the `ci` profile optimises (the known-answer
# tests are heavy) and keeps debug assertions and overflow checks on.
test: lint
	$(CARGO) test --locked --profile ci

demo: deps
	$(CARGO) run --locked --release -- demo --out $(DEMO_OUT)

bench: deps
	$(CARGO) bench --locked --bench conform
	$(CARGO) bench --locked --bench model
	$(CARGO) bench --locked --bench stereo

clean:
	$(CARGO) clean
	rm -rf $(DEMO_OUT)
