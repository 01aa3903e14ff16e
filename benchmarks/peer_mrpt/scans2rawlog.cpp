// scans2rawlog: write an MRPT rawlog from a plain-text list of scans with odometry.
//
// Why not carmen2rawlog: in MRPT 2.5.8 it gives every observation of these logs the same
// timestamp (so icp-slam's odometry integration does nothing), and rbpf-slam needs the
// action/sensory-frame layout, which carmen2rawlog does not write. The input is written by
// benchmarks/peer_mrpt.py from scanguard's reader, so MRPT sees exactly the scans, stamps,
// odometry and beam geometry that scanguard sees.
//
// Input, one scan a line: stamp odom_x odom_y odom_theta max_range aperture n r_1 .. r_n
// (a range that is not finite, <= 0 or >= max_range is an invalid beam).
// Usage: scans2rawlog IN.txt OUT.rawlog obs|sf
#include <mrpt/io/CFileGZOutputStream.h>
#include <mrpt/obs/CActionCollection.h>
#include <mrpt/obs/CActionRobotMovement2D.h>
#include <mrpt/obs/CObservation2DRangeScan.h>
#include <mrpt/obs/CObservationOdometry.h>
#include <mrpt/obs/CSensoryFrame.h>
#include <mrpt/serialization/CArchive.h>

#include <cmath>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>

using namespace mrpt::obs;
using mrpt::poses::CPose2D;

int main(int argc, char** argv)
{
	if (argc != 4)
	{
		std::cerr << "usage: scans2rawlog IN.txt OUT.rawlog obs|sf\n";
		return 2;
	}
	std::ifstream in(argv[1]);
	if (!in)
	{
		std::cerr << "cannot read " << argv[1] << "\n";
		return 1;
	}
	const std::string mode = argv[3];
	mrpt::io::CFileGZOutputStream fo(argv[2]);
	auto arch = mrpt::serialization::archiveFrom(fo);
	CActionRobotMovement2D::TMotionModelOptions motion;  // MRPT's defaults
	std::string line;
	CPose2D last_odo;
	bool first = true;
	size_t count = 0;
	while (std::getline(in, line))
	{
		std::istringstream s(line);
		double t, x, y, th, max_range, aperture;
		size_t n;
		if (!(s >> t >> x >> y >> th >> max_range >> aperture >> n)) continue;
		auto scan = CObservation2DRangeScan::Create();
		scan->sensorLabel = "LASER";
		scan->aperture = static_cast<float>(aperture);
		scan->maxRange = static_cast<float>(max_range);
		scan->rightToLeft = true;
		scan->resizeScan(n);
		for (size_t i = 0; i < n; i++)
		{
			double r = 0;
			s >> r;
			const bool ok = std::isfinite(r) && r > 0 && r < max_range;
			scan->setScanRange(i, static_cast<float>(ok ? r : max_range));
			scan->setScanRangeValidity(i, ok);
		}
		const auto stamp = mrpt::Clock::fromDouble(t);
		scan->timestamp = stamp;
		const CPose2D odo(x, y, th);
		if (mode == "obs")
		{
			auto o = CObservationOdometry::Create();
			o->timestamp = stamp;
			o->odometry = odo;
			o->sensorLabel = "ODOMETRY";
			arch << *o << *scan;
		}
		else
		{
			CActionCollection acts;
			CActionRobotMovement2D act;
			act.timestamp = stamp;
			act.computeFromOdometry(first ? CPose2D() : odo - last_odo, motion);
			acts.insert(act);
			CSensoryFrame sf;
			sf.insert(scan);
			arch << acts << sf;
		}
		last_odo = odo;
		first = false;
		count++;
	}
	std::cout << count << " scans written to " << argv[2] << " (" << mode << ")\n";
	return count > 0 ? 0 : 1;
}
