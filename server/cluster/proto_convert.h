// Conversions between shard.proto's messages and the index's types, shared by the front (front.cc) and
// the shard (shard_server.cc). Internal to server/cluster: the generated header is not public.
#pragma once

#include <span>
#include <vector>

#include <google/protobuf/repeated_field.h>
#include <google/protobuf/repeated_ptr_field.h>

#include "index/image_index.h"
#include "server/cluster/shard.pb.h"
#include "sift/types.h"

namespace oxbow::cluster {

// The gRPC metadata key of a shard's write sequence (index::ImageIndex::write_sequence), on every
// answer of a loaded shard: what the front compares replicas by (front.h). Reads carry it as of the
// start of the call, writes as of their commit.
inline constexpr const char* kWriteSequenceKey = "oxbow-write-sequence";
// The gRPC metadata key naming the search a call belongs to (a front's random key per search): a shard
// keeps that search's index::search::Source between its calls (ShardServer), so each stage reads the
// candidates' features and bags the previous stages read, from one snapshot.
inline constexpr const char* kSearchKey = "oxbow-search";
// The gRPC metadata key naming the collection a call acts on (api/collections.h; a shard serving --data
// holds its partition of each); a call without it acts on the collection "default".
inline constexpr const char* kCollectionKey = "oxbow-collection";

// Keypoints as shard.proto packs them: x, y, scale, orientation of each, in order.
inline constexpr int kKeypointValues = 4;
std::vector<sift::Keypoint> KeypointsFrom(const google::protobuf::RepeatedField<float>& values);
void PutKeypoints(std::span<const sift::Keypoint> keypoints, google::protobuf::RepeatedField<float>* out);

std::vector<index::QueryTerm> TermsFrom(const google::protobuf::RepeatedPtrField<Term>& terms);
void PutTerms(std::span<const index::QueryTerm> terms, google::protobuf::RepeatedPtrField<Term>* out);

index::ImageRecord FromProto(const Record& r);
void PutRecord(const index::ImageRecord& record, Record* out);

}  // namespace oxbow::cluster
