#!/bin/sh
# Builds the Debian package of conformd from a built binary:
#   packaging/deb/build.sh BINARY OUTDIR [COMPRESSION]
# writes OUTDIR/conformd_<version>-1_<arch>.deb and prints its path. `make deb` runs it
# on the release binary; the package test (tests/package.rs) on the tested one.
# Needs dpkg-dev (dpkg-shlibdeps), binutils (strip) and help2man (the manual page).
set -eu

binary=${1:?usage: build.sh BINARY OUTDIR [xz|gzip]}
out=${2:?usage: build.sh BINARY OUTDIR [xz|gzip]}
compression=${3:-xz}
here=$(cd "$(dirname "$0")" && pwd)
top=$(cd "$here/../.." && pwd)

[ -x "$binary" ] || { echo "build.sh: $binary is not an executable (build it first)" >&2; exit 1; }
for tool in dpkg-deb dpkg-shlibdeps strip gzip help2man; do
    command -v "$tool" >/dev/null || { echo "build.sh: $tool not found (apt-get install dpkg-dev binutils help2man)" >&2; exit 1; }
done

version=$(sed -n 's/^version = "\(.*\)"$/\1/p' "$top/Cargo.toml" | head -n 1)
[ -n "$version" ] || { echo "build.sh: no version in Cargo.toml" >&2; exit 1; }
arch=$(dpkg --print-architecture)
revision=1
# who built it: Debian's DEBFULLNAME and DEBEMAIL when set
maintainer="${DEBFULLNAME:-conformd developers} <${DEBEMAIL:-conformd@example.org}>"
# the package's dates are the last commit's, so the same tree gives the same package
SOURCE_DATE_EPOCH=${SOURCE_DATE_EPOCH:-$(git -C "$top" log -1 --format=%ct 2>/dev/null || date +%s)}
export SOURCE_DATE_EPOCH

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
root=$work/root
doc=$root/usr/share/doc/conformd

install -d -m 755 "$root/usr/bin" "$root/lib/systemd/system" "$root/etc/conformd" \
    "$root/usr/share/conformd/measurements" "$doc/examples" "$root/usr/share/man/man1" \
    "$root/usr/share/lintian/overrides" "$root/DEBIAN"
install -m 755 "$binary" "$root/usr/bin/conformd"
strip --remove-section=.comment --remove-section=.note --strip-unneeded "$root/usr/bin/conformd"

# the units as the repository has them, pointed at the packaged binary and documentation,
# without the comment on installing them by hand
for unit in conformd conformd-worker; do
    {
        echo "$(sed -n 1p "$top/systemd/$unit.service") (installed by the conformd package)"
        sed -n '/^\[Unit\]/,$p' "$top/systemd/$unit.service" |
            sed 's#/usr/local/bin/conformd#/usr/bin/conformd#;
                 s#file:///usr/local/share/doc/conformd/README.md#file:///usr/share/doc/conformd/README.md.gz#'
    } > "$root/lib/systemd/system/$unit.service"
    chmod 644 "$root/lib/systemd/system/$unit.service"
done

# configuration: the station file and the rig it names are conffiles, edited in place
install -m 644 "$top/config/station.example.toml" "$root/etc/conformd/station.toml"
install -m 644 "$top/config/rig.example.toml" "$root/etc/conformd/rig.example.toml"
for f in "$top"/config/*.example.toml; do
    install -m 644 "$f" "$doc/examples/"
done
install -m 644 "$top"/config/measurements/*.toml "$root/usr/share/conformd/measurements/"

# documentation: README, copyright, changelog (compressed as Debian does)
gzip -9n < "$top/README.md" > "$doc/README.md.gz"
install -m 644 "$here/copyright" "$doc/copyright"
install -m 644 "$here/lintian-overrides" "$root/usr/share/lintian/overrides/conformd"
# the manual page from the program's own --help (every command's: `conformd help CMD`)
cat > "$work/see-also" <<'SEE'
[SEE ALSO]
\fBconformd help\fR \fICOMMAND\fR: the options of each command.
.PP
/usr/share/doc/conformd/README.md.gz: the station, its files and formats.
SEE
help2man --no-info --version-string="$version" --include "$work/see-also" \
    --name "photogrammetry capture-station daemon: conform a template mesh onto scans" \
    --output "$work/conformd.1" "$root/usr/bin/conformd"
gzip -9n < "$work/conformd.1" > "$root/usr/share/man/man1/conformd.1.gz"
chmod 644 "$root/usr/share/man/man1/conformd.1.gz"
date=$(date -u -R -d "@$SOURCE_DATE_EPOCH")
printf 'conformd (%s-%s) unstable; urgency=medium\n\n  * Built from the conformd source tree (make deb).\n\n -- %s  %s\n' \
    "$version" "$revision" "$maintainer" "$date" | gzip -9n > "$doc/changelog.Debian.gz"
chmod 644 "$doc/README.md.gz" "$doc/changelog.Debian.gz"

# maintainer scripts and control files
for script in postinst prerm postrm; do
    install -m 755 "$here/$script" "$root/DEBIAN/$script"
done
printf '/etc/conformd/station.toml\n/etc/conformd/rig.example.toml\n' > "$root/DEBIAN/conffiles"
chmod 644 "$root/DEBIAN/conffiles"

# the shared libraries' packages, as dpkg-shlibdeps finds them; besides them the font the
# plots' labels are drawn in and the three.js the capture page's 3D view is served from
mkdir -p "$work/src/debian"
printf 'Source: conformd\n\nPackage: conformd\nArchitecture: any\n' > "$work/src/debian/control"
shlibs=$(cd "$work/src" && dpkg-shlibdeps -O -e "$root/usr/bin/conformd" 2>/dev/null |
    sed -n 's/^shlibs:Depends=//p')
[ -n "$shlibs" ] || { echo "build.sh: dpkg-shlibdeps found no libraries" >&2; exit 1; }
size=$(du -k -s --exclude=DEBIAN "$root" | cut -f 1)
cat > "$root/DEBIAN/control" <<CONTROL
Package: conformd
Version: $version-$revision
Architecture: $arch
Maintainer: $maintainer
Installed-Size: $size
Depends: $shlibs, passwd, fonts-dejavu-core, libjs-three
Section: science
Priority: optional
Description: photogrammetry capture-station daemon with template mesh conformation
 conformd drives a 3D photogrammetry capture station (livestock posture crates,
 human body-scanning booths): it triggers the cameras over V4L2 and a serial
 trigger box, reconstructs each capture with OpenCV stereo, conforms a generic
 pig or body mesh onto every scan so that every result has the template's
 vertices in correspondence, and measures it (girths, lengths, volume, weight).
 .
 The package installs the binary, the systemd units of the station daemon and of
 a worker, the station's configuration in /etc/conformd, and the measurement
 definitions; it makes the conformd system user and its state directory
 /var/lib/conformd. Edit /etc/conformd/station.toml, run
 "conformd check /etc/conformd/station.toml", then enable conformd.service.
CONTROL
(cd "$root" && find . -path ./DEBIAN -prune -o -type f -print | sed 's#^\./##' | sort |
    xargs md5sum > DEBIAN/md5sums)
chmod 644 "$root/DEBIAN/control" "$root/DEBIAN/md5sums"
find "$root" -newermt "@$SOURCE_DATE_EPOCH" -exec touch --no-dereference -d "@$SOURCE_DATE_EPOCH" {} +

mkdir -p "$out"
deb="$out/conformd_${version}-${revision}_${arch}.deb"
dpkg-deb --root-owner-group -Z"$compression" --build "$root" "$deb" >/dev/null
echo "$deb"
