# conformd — `make demo` runs the main job on built-in defaults, `make test` runs every
# test. Both first install the system packages the build needs when they are missing.

APT_PACKAGES := libopencv-dev clang libclang-dev pkg-config libudev-dev
CARGO ?= cargo
DEMO_OUT ?= demo-output

.PHONY: all deps build test test-fast demo bench clean

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

# Every test in a debug build (debug assertions on; the heavy known-answer tests are
# listed as ignored there), then every test in release, where the heavy ones run.
test: deps
	$(CARGO) test --locked
	$(CARGO) test --locked --release

test-fast: deps
	$(CARGO) test --locked

demo: deps
	$(CARGO) run --locked --release -- demo --out $(DEMO_OUT)

bench: deps
	$(CARGO) bench --locked --bench conform
	$(CARGO) bench --locked --bench model
	$(CARGO) bench --locked --bench stereo

clean:
	$(CARGO) clean
	rm -rf $(DEMO_OUT)
